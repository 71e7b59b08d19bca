//! Demonstrations over HTTP: recorded by a job, exported, re-imported, refused line by line.

use crate::serve_support;

use serde_json::json;
use serve_support::Server;

fn export(server: &Server, id: i64) -> String {
    ureq::get(format!("{}/api/demonstrations/{id}", server.base))
        .header("Authorization", format!("Bearer {}", server.admin))
        .call()
        .unwrap()
        .into_body()
        .read_to_string()
        .unwrap()
}

#[test]
fn a_recorded_demonstration_round_trips_and_a_bad_import_stores_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(dir.path(), &[("CELLD_STEP_PERIOD_MS", "5")]);
    let admin = server.admin.clone();

    let job = server.create_job(
        &admin,
        json!({"controller": "expert", "seed": 8, "demonstration": true}),
    );
    let done = server.wait_final(job["id"].as_i64().unwrap());
    assert_eq!(done["status"], "succeeded", "{done}");
    let (_, list) = server.get("/api/demonstrations", Some(&admin));
    let recorded = list["items"][0].clone();
    assert_eq!(recorded["source"], "recorded", "{list}");
    assert_eq!(recorded["job_id"], job["id"]);
    let steps = recorded["steps"].as_i64().unwrap();
    assert!(
        steps > 10 && steps <= done["steps"].as_i64().unwrap(),
        "{recorded}"
    );

    // The steps are the job's own: each demonstration action is the move the job stored.
    let first = export(&server, recorded["id"].as_i64().unwrap());
    assert_eq!(first.lines().count() as i64, steps);
    let stored = server.steps(job["id"].as_i64().unwrap());
    for line in first.lines() {
        let step: serde_json::Value = serde_json::from_str(line).unwrap();
        let index = step["step"].as_u64().unwrap() as usize;
        assert_eq!(step["action"], stored[index]["action"], "step {index}");
    }

    // Export → import → export gives the same bytes.
    let (status, imported) = server.post_raw(
        "/api/demonstrations?name=copy",
        &admin,
        "application/x-ndjson",
        first.as_bytes(),
    );
    assert_eq!(status, 201, "{imported}");
    assert_eq!(imported["source"], "imported");
    assert_eq!(imported["steps"], steps);
    let second = export(&server, imported["id"].as_i64().unwrap());
    assert_eq!(second, first);

    // One bad line: refused with its number, nothing stored.
    let mut lines: Vec<&str> = first.lines().collect();
    lines[2] = r#"{"episode":0,"step":2,"state":[1,2,3],"action":[0,0,0,0,0,0],"actor":"position","scale":0.5}"#;
    let bad = lines.join("\n");
    let (status, refused) = server.post_raw(
        "/api/demonstrations",
        &admin,
        "application/x-ndjson",
        bad.as_bytes(),
    );
    assert_eq!(status, 422, "{refused}");
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains("line 3"),
        "{refused}"
    );
    let (_, after) = server.get("/api/demonstrations", Some(&admin));
    assert_eq!(
        after["items"].as_array().unwrap().len(),
        2,
        "nothing of the bad import stored"
    );

    // A training run on them is refused before it starts: one episode each is too few, and a
    // demonstration named twice would count twice.
    let one_episode = recorded["id"].as_i64().unwrap();
    for (named, says) in [
        (
            json!([one_episode, imported["id"]]),
            "2 episodes with steps; at least 10",
        ),
        (json!([one_episode, one_episode]), "named twice"),
    ] {
        let (status, refused) = server.post(
            "/api/training",
            Some(&admin),
            Some(json!({ "demonstrations": named })),
        );
        assert_eq!(status, 422, "{refused}");
        let message = refused["error"]["message"].as_str().unwrap();
        assert!(message.contains(says), "{message}");
    }
    let (_, runs) = server.get("/api/training", Some(&admin));
    assert_eq!(runs["items"].as_array().unwrap().len(), 0, "{runs}");

    // Roles, then delete.
    let operator = server.token("operator");
    let (status, _) = server.post_raw(
        "/api/demonstrations",
        &operator,
        "application/x-ndjson",
        b"",
    );
    assert_eq!(status, 403);
    let id = imported["id"].as_i64().unwrap();
    let delete = |token: &str| {
        ureq::Agent::config_builder()
            .http_status_as_error(false)
            .build()
            .new_agent()
            .delete(format!("{}/api/demonstrations/{id}", server.base))
            .header("Authorization", format!("Bearer {token}"))
            .call()
            .unwrap()
            .status()
            .as_u16()
    };
    assert_eq!(delete(&operator), 403);
    assert_eq!(delete(&admin), 204);
    assert_eq!(delete(&admin), 404);
    let (status, _) = server.get(&format!("/api/demonstrations/{id}"), Some(&admin));
    assert_eq!(status, 404);
}
