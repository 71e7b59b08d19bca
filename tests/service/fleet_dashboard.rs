//! The dashboard's Fleet view in a real headless Chromium against two `celld serve --fast` cells
//! replicating to one throwaway PostgreSQL: both cells listed with their counters, the cell
//! picker narrowing the fleet's jobs and stats to one cell, a fleet activation's outcomes as the
//! API records them, no activate button for a viewer, no Fleet entry on a cell without a fleet,
//! and the view's message when PostgreSQL stops while the rest of the dashboard works on.
//! Screenshots are saved under `target/tmp/dashboard-screenshots/`.

use crate::browser_support;
use crate::postgres_support as postgres;
use crate::serve_support;

use browser_support::Browser;
use serde_json::{Value, json};
use serve_support::Server;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Replication and the view's refresh (every 3 s) both lie between a change and the page.
const WAIT: Duration = Duration::from_secs(45);

fn screenshots() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dashboard-screenshots")
}

fn text_of(browser: &Browser, css: &str) -> String {
    if browser.exists(css) {
        browser.find(css).text()
    } else {
        String::new()
    }
}

/// Runs `script` (which may use `arguments[0]`...) and returns its value.
fn js(browser: &Browser, script: &str, args: Vec<Value>) -> Value {
    browser.execute(script, args)
}

/// The fleet jobs table's rows as `(cell, job id, steps)`, read in one script (the view redraws
/// the table when the fleet changes).
fn job_rows(browser: &Browser) -> Vec<(String, i64, u64)> {
    let rows = js(
        browser,
        "return [...document.querySelectorAll('#fleet-jobs tbody tr')].map((r) =>
           [r.dataset.cell, Number(r.dataset.jobId), Number(r.querySelector('[data-steps]').dataset.steps)]);",
        vec![],
    );
    rows.as_array()
        .unwrap()
        .iter()
        .map(|row| {
            (
                row[0].as_str().unwrap().to_string(),
                row[1].as_i64().unwrap(),
                row[2].as_u64().unwrap(),
            )
        })
        .collect()
}

/// A counter of `cell` in the cells table, as shown.
fn counter(browser: &Browser, cell: &str, name: &str) -> String {
    text_of(
        browser,
        &format!("#fleet-cells tr[data-cell='{cell}'] td[data-counter='{name}']"),
    )
}

/// A headless Chromium; none (said so) where chromedriver is not installed, which fails under CI.
fn browser() -> Option<(Browser, PathBuf)> {
    let Some(browser) = Browser::start() else {
        if std::env::var_os("CI").is_some() {
            panic!("CI is set but chromedriver is not installed (.ci/run installs it)");
        }
        eprintln!("skipping the fleet browser test: chromedriver is not installed");
        return None;
    };
    let shots = screenshots();
    browser.set_screenshot_dir(Some(&shots));
    Some((browser, shots))
}

fn fleet_cell(dir: &Path, url: &str, cell_id: &str) -> Server {
    Server::start(
        dir,
        &[
            ("CELLD_FAST", "true"),
            ("CELLD_FLEET_URL", url),
            ("CELLD_CELL_ID", cell_id),
        ],
    )
}

/// Runs an expert job with `seed` on `server` to its end; answers the stored job.
fn run_job(server: &Server, seed: u64) -> Value {
    let job = server.create_job(&server.admin, json!({"controller": "expert", "seed": seed}));
    let done = server.wait_final(job["id"].as_i64().unwrap());
    assert_eq!(done["status"], "succeeded", "{done}");
    done
}

#[test]
fn the_fleet_view_lists_the_cells_and_filters_jobs_by_cell() {
    let Some((browser, shots)) = browser() else {
        return;
    };
    // A cluster of its own: the test stops it.
    let cluster = postgres::Postgres::start();
    let url = cluster.url();
    let (dir_a, dir_b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let cell_a = fleet_cell(dir_a.path(), &url, "cell-a");
    let cell_b = fleet_cell(dir_b.path(), &url, "cell-b");

    // One job on each cell: the independent answer is each cell's own record of it.
    let job_a = run_job(&cell_a, 7);
    let job_b = run_job(&cell_b, 11);
    let (id_a, id_b) = (job_a["id"].as_i64().unwrap(), job_b["id"].as_i64().unwrap());
    let steps_b = job_b["steps"].as_u64().unwrap();
    // The bundled policy's first-start evaluation ends before the registry is looked at.
    for cell in [&cell_a, &cell_b] {
        let bundled = cell.wait_evaluated(1, WAIT);
        assert_eq!(bundled["evaluation"]["status"], "done", "{bundled}");
    }
    let (_, bundled) = cell_a.get("/api/policies/1", Some(&cell_a.admin));
    let sha256 = bundled["sha256"].as_str().unwrap().to_string();

    // Cell A's dashboard, signed in as admin: the Fleet entry shows.
    browser.set_window_size(1366, 900);
    browser.goto(&cell_a.signin_url.clone().expect("a sign-in link"));
    browser.wait_until("signed in as admin", WAIT, |b| {
        text_of(b, "#whoami").contains("admin")
    });
    browser.wait_until("the Fleet entry", WAIT, |b| {
        b.exists("#nav a[data-page=fleet][data-fleet=member]")
    });
    let entry = browser.find("#nav a[data-page=fleet]");
    assert!(entry.is_displayed());
    entry.click();

    // Both cells, this one marked, each with the one good part it made.
    browser.wait_until("both cells with one good part each", WAIT, |b| {
        ["cell-a", "cell-b"]
            .iter()
            .all(|cell| counter(b, cell, "processed") == "1" && counter(b, cell, "good") == "1")
    });
    let marked = |cell: &str| {
        browser
            .find(&format!("#fleet-cells tr[data-cell='{cell}']"))
            .attribute("data-this-cell")
    };
    assert_eq!(marked("cell-a").as_deref(), Some("true"));
    assert_eq!(marked("cell-b").as_deref(), Some("false"));
    assert_eq!(counter(&browser, "cell-b", "defective"), "0");

    // All cells: both jobs, each under its own cell.
    browser.wait_until("both jobs in the fleet's table", WAIT, |b| {
        let rows = job_rows(b);
        rows.iter()
            .any(|(cell, id, _)| cell == "cell-a" && *id == id_a)
            && rows
                .iter()
                .any(|(cell, id, _)| cell == "cell-b" && *id == id_b)
    });
    browser.screenshot(&shots.join("fleet-1-all-cells.png"));

    // Cell B picked: its job alone, as cell B stored it, and stats over that one job.
    browser.select_value("#fleet-cell", "cell-b");
    browser.wait_until("cell B's job alone", WAIT, |b| {
        job_rows(b) == vec![("cell-b".to_string(), id_b, steps_b)]
            && b.find("#fleet-stats").attribute("data-jobs").as_deref() == Some("1")
    });
    assert!(
        browser.current_url().contains("#/fleet?cell=cell-b"),
        "{}",
        browser.current_url()
    );
    assert_eq!(
        browser.find("#fleet-cell").property("value"),
        json!("cell-b")
    );
    browser.screenshot(&shots.join("fleet-2-cell-b.png"));

    // The bundled policy on both cells; activating it where it passed shows each cell's
    // outcome as the fleet records it.
    let row = format!("#fleet-policies tr[data-sha256='{sha256}']");
    browser.wait_until("the bundled policy on both cells", WAIT, |b| {
        b.exists(&format!("{row} td[data-cell='cell-a'][data-status]"))
            && b.exists(&format!("{row} td[data-cell='cell-b'][data-status]"))
    });
    js(
        &browser,
        "window.confirm = () => true;
         document.querySelector(arguments[0] + ' button[data-action=activate]').click();",
        vec![json!(row)],
    );
    browser.wait_until("both cells' outcomes", WAIT, |b| {
        b.find_all("#fleet-activation-results li").len() == 2
    });
    let activation: i64 = browser
        .find("#fleet-activation")
        .attribute("data-activation-id")
        .unwrap()
        .parse()
        .unwrap();
    let (status, request) = cell_a.get(
        &format!("/api/fleet/activations/{activation}"),
        Some(&cell_a.admin),
    );
    assert_eq!(status, 200, "{request}");
    assert_eq!(request["sha256"], sha256.as_str());
    let mut recorded: Vec<(String, String)> = request["results"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            (
                r["cell_id"].as_str().unwrap().to_string(),
                r["outcome"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    recorded.sort();
    let shown = js(
        &browser,
        "return [...document.querySelectorAll('#fleet-activation-results li')].map((li) =>
           [li.dataset.cell, li.dataset.outcome]).sort();",
        vec![],
    );
    assert_eq!(shown, json!(recorded));
    browser.screenshot(&shots.join("fleet-3-activation.png"));

    // A viewer sees the registry and no activate button.
    let viewer = cell_a.token("viewer");
    browser.find("#signout").click();
    browser.wait_until("the sign-in form", WAIT, |b| b.exists("#token"));
    browser.find("#token").send_keys(&viewer);
    browser.find("#signin-submit").click();
    browser.wait_until("signed in as viewer", WAIT, |b| {
        text_of(b, "#whoami").contains("viewer")
    });
    browser.goto(&format!("{}/#/fleet", cell_a.base));
    browser.wait_until("the registry for a viewer", WAIT, |b| b.exists(&row));
    assert!(
        !browser.exists("[data-action=activate]"),
        "a viewer sees an activate button"
    );

    // A cell without a fleet: no Fleet entry.
    let dir_c = tempfile::tempdir().unwrap();
    let alone = Server::start(dir_c.path(), &[("CELLD_FAST", "true")]);
    browser.goto(&alone.signin_url.clone().expect("a sign-in link"));
    browser.wait_until("the cell says it is in no fleet", WAIT, |b| {
        b.exists("#nav a[data-page=fleet][data-fleet=none]")
    });
    assert!(!browser.find("#nav a[data-page=fleet]").is_displayed());

    // PostgreSQL stops: the view says so; the live page still works.
    browser.goto(&format!("{}/#/fleet", cell_a.base));
    browser.wait_until("the fleet view", WAIT, |b| b.exists(&row));
    cluster.stop();
    browser.wait_until("the view says the fleet is unavailable", WAIT, |b| {
        text_of(b, "#fleet-status").contains("fleet_unavailable")
    });
    assert!(browser.find("#nav a[data-page=fleet]").is_displayed());
    browser.screenshot(&shots.join("fleet-4-unavailable.png"));
    browser.goto(&format!("{}/#/live", cell_a.base));
    browser.wait_until("the live page", WAIT, |b| {
        b.exists("#machine-state[data-state=Complete]")
    });
    let (status, cell) = cell_a.get("/api/cell", Some(&cell_a.admin));
    assert_eq!(status, 200, "{cell}");
    eprintln!("screenshots in {}", shots.display());
}
