//! The dashboard in a real headless Chromium against a real `celld serve --fast` with a fresh
//! database: sign in with the printed link, start a job from the page and watch it succeed,
//! see its plots drawn, e-stop and reset, the policy gate's answer, what a viewer may not do,
//! a tablet-sized window, and the message when the server goes away; and, on a cell driven
//! through the drivers, a latched robot driver shown with its reason and reset from the page.
//! Screenshots are saved
//! under `target/tmp/dashboard-screenshots/` for a person to look at.

use crate::browser_support;
use crate::drivers_support;
use crate::serve_support;

use browser_support::Browser;
use drivers_support::TwinServer;
use serde_json::{Value, json};
use serve_support::Server;
use std::path::PathBuf;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(30);

fn screenshots() -> PathBuf {
    PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dashboard-screenshots")
}

/// Runs `script` (which may use `arguments[0]`) and returns its value.
fn js(browser: &Browser, script: &str) -> Value {
    browser.execute(script, vec![])
}

/// How many points each dataset of the chart on `canvas_id` holds, and how many of the drawn
/// elements Chart.js placed inside the plot area.
fn chart_points(browser: &Browser, canvas_id: &str) -> (Vec<u64>, u64) {
    let answer = browser.execute(
        "const chart = Chart.getChart(document.getElementById(arguments[0]));
         if (!chart) return null;
         const area = chart.chartArea;
         let inside = 0;
         chart.data.datasets.forEach((_, i) => chart.getDatasetMeta(i).data.forEach((e) => {
           if (e.x >= area.left - 1 && e.x <= area.right + 1 && e.y >= area.top - 1 && e.y <= area.bottom + 1) inside++;
         }));
         return { counts: chart.data.datasets.map((d) => d.data.length), inside };",
        vec![json!(canvas_id)],
    );
    assert!(!answer.is_null(), "no chart on #{canvas_id}");
    let counts = answer["counts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_u64().unwrap())
        .collect();
    (counts, answer["inside"].as_u64().unwrap())
}

/// Pixels of the canvas painted within ±12 of the colour `rgb`: proof that a series was drawn,
/// independent of the chart library's own bookkeeping.
fn painted_pixels(browser: &Browser, canvas_id: &str, rgb: [u8; 3]) -> u64 {
    browser
        .execute(
            "const canvas = document.getElementById(arguments[0]);
             const pixels = canvas.getContext('2d').getImageData(0, 0, canvas.width, canvas.height).data;
             const [r, g, b] = arguments[1];
             let n = 0;
             for (let i = 0; i < pixels.length; i += 4) {
               if (pixels[i + 3] > 200 && Math.abs(pixels[i] - r) <= 12 && Math.abs(pixels[i + 1] - g) <= 12 && Math.abs(pixels[i + 2] - b) <= 12) n++;
             }
             return n;",
            vec![json!(canvas_id), json!(rgb)],
        )
        .as_u64()
        .unwrap()
}

fn text_of(browser: &Browser, css: &str) -> String {
    if browser.exists(css) {
        browser.find(css).text()
    } else {
        String::new()
    }
}

/// A headless Chromium saving its screenshots under [`screenshots`]; none (said so) where
/// chromedriver is not installed, which fails under CI.
fn browser() -> Option<(Browser, PathBuf)> {
    let Some(browser) = Browser::start() else {
        if std::env::var_os("CI").is_some() {
            panic!("CI is set but chromedriver is not installed (.ci/run installs it)");
        }
        eprintln!("skipping the browser test: chromedriver is not installed");
        return None;
    };
    let shots = screenshots();
    browser.set_screenshot_dir(Some(&shots));
    Some((browser, shots))
}

#[test]
fn dashboard_drives_the_cell_in_a_real_browser() {
    let Some((browser, shots)) = browser() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // A gate of 1: a policy must succeed in every episode of its evaluation. The bundled flat
    // `td3` baseline, uploaded below, succeeds in none, so the page can show the gate's
    // refusal.
    let mut server = Server::start(
        dir.path(),
        &[
            ("CELLD_FAST", "true"),
            ("CELLD_ACTIVATION_THRESHOLD", "1"),
            ("CELLD_EVALUATION_EPISODES", "1000"),
        ],
    );
    let signin_url = server
        .signin_url
        .clone()
        .expect("the first start prints a sign-in link");
    assert!(signin_url.contains("#token="), "{signin_url}");
    browser.set_window_size(1366, 900);

    // Sign in with the printed link; the token leaves the address bar.
    browser.goto(&signin_url);
    browser.wait_until("signed in as admin", WAIT, |b| {
        text_of(b, "#whoami").contains("admin")
    });
    assert!(
        !browser.current_url().contains("token="),
        "the token stays out of the address: {}",
        browser.current_url()
    );

    // Start a job from the page and watch it reach `succeeded` in the live view.
    browser.wait_until("the controller list", WAIT, |b| {
        b.exists("#start-controller option[value=expert]")
    });
    browser.select_value("#start-controller", "expert");
    browser.find("#start-seed").send_keys("7");
    browser.find("#start-job").click();
    browser.wait_until("the job succeeds in the live view", WAIT, |b| {
        b.exists("#live-job[data-status=succeeded]")
    });
    let job_id: i64 = browser
        .find("#live-job")
        .attribute("data-job-id")
        .unwrap()
        .parse()
        .unwrap();
    let (_, job) = server.get(&format!("/api/jobs/{job_id}"), Some(&server.admin));
    assert_eq!(job["status"], "succeeded");
    assert_eq!(job["controller"], "expert");
    assert_eq!(job["seed"], 7, "the page sent the seed typed in");
    let steps = job["steps"].as_u64().unwrap();
    assert!(steps > 10, "{job}");
    // Every stored step is on the live plots, inside their plot areas: |P|, |O| and the σ of
    // the sideways estimate.
    browser.wait_until("the live plots hold every step", WAIT, |b| {
        chart_points(b, "chart-live-errors").0 == vec![steps, steps, steps]
    });
    let (legs, inside) = chart_points(&browser, "chart-live-legs");
    assert_eq!(legs, vec![steps; 6]);
    assert_eq!(inside, 6 * steps);
    let (actors, _) = chart_points(&browser, "chart-live-actor");
    assert_eq!(actors.iter().sum::<u64>(), steps, "one bar per step");
    assert!(painted_pixels(&browser, "chart-live-errors", [31, 95, 191]) > 100);
    browser.screenshot(&shots.join("1-live-after-job.png"));

    // The job's page: status, plots drawn, CSV download offered.
    browser
        .find(&format!("#live-job a[href='#/jobs/{job_id}']"))
        .click();
    browser.wait_until("the job page", WAIT, |b| {
        text_of(b, "#job-status") == "succeeded"
    });
    browser.wait_until("the job plots hold every step", WAIT, |b| {
        chart_points(b, "chart-job-trajectory").0.first() == Some(&steps)
    });
    for (canvas, per_step) in [
        ("chart-job-errors", 3),
        ("chart-job-legs", 6),
        ("chart-job-trajectory", 1),
        ("chart-job-trajectory-side", 1),
    ] {
        let (_, inside) = chart_points(&browser, canvas);
        assert!(
            inside >= per_step * steps,
            "{canvas}: {inside} points inside the plot area, expected {}",
            per_step * steps
        );
    }
    assert!(painted_pixels(&browser, "chart-job-errors", [31, 95, 191]) > 100);
    assert!(painted_pixels(&browser, "chart-job-trajectory", [27, 127, 59]) > 50);
    assert!(browser.find("#job-csv").is_displayed());
    browser.screenshot(&shots.join("2-job-page.png"));

    // The steps table: a row per step; the expert proposes nothing of its own, so no rule
    // changed a move.
    let rows = |b: &Browser, css: &str| {
        js(
            b,
            &format!("return document.querySelectorAll('{css}').length"),
        )
        .as_u64()
        .unwrap()
    };
    assert_eq!(rows(&browser, "#job-steps tbody tr"), steps);
    assert_eq!(rows(&browser, "#job-steps tr.ruled"), 0);

    // History: the job is listed, the stats charts are drawn.
    browser.goto(&format!("{}/#/jobs", server.base));
    browser.wait_until("the history table", WAIT, |b| {
        b.exists(&format!("a[href='#/jobs/{job_id}']"))
    });
    assert_eq!(
        chart_points(&browser, "chart-stats-controller").0,
        vec![1, 1]
    );
    browser.screenshot(&shots.join("3-history.png"));

    // A learned policy's job: every row a rule changed is marked, with its rules as tags, in
    // the stored order.
    let learned = server.create_job(
        &server.admin,
        json!({"controller": "hierarchical-swift-cells", "seed": 7}),
    );
    let learned_id = learned["id"].as_i64().unwrap();
    server.wait_final(learned_id);
    let stored = server.steps(learned_id);
    let ruled: Vec<&Value> = stored
        .iter()
        .filter(|s| !s["rules"].as_array().unwrap().is_empty())
        .collect();
    assert!(!ruled.is_empty(), "some rule changed some move");
    browser.goto(&format!("{}/#/jobs/{learned_id}", server.base));
    browser.wait_until("the learned job's steps table", WAIT, |b| {
        rows(b, "#job-steps tbody tr") == stored.len() as u64
    });
    assert_eq!(rows(&browser, "#job-steps tr.ruled"), ruled.len() as u64);
    assert_eq!(
        text_of(&browser, "#job-ruled-count"),
        ruled.len().to_string()
    );
    let first = ruled[0];
    let tags = js(
        &browser,
        &format!(
            "return [...document.querySelectorAll('#job-steps tr[data-step=\"{}\"] .tag')].map((t) => t.textContent)",
            first["step"]
        ),
    );
    assert_eq!(tags, first["rules"]);
    js(
        &browser,
        "document.getElementById('job-steps').scrollIntoView()",
    );
    browser.screenshot(&shots.join("3b-learned-job-steps.png"));

    // E-stop acts at once; reset asks first (the confirmation is answered yes here).
    browser.goto(&format!("{}/#/live", server.base));
    browser.wait_until("the e-stop button", WAIT, |b| b.exists("#estop"));
    browser.find("#estop").click();
    browser.wait_until("the e-stop shows latched", WAIT, |b| {
        b.exists("#estop-state[data-latched=true]")
    });
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert_eq!(cell["estop_latched"], true);
    assert_eq!(cell["machine"]["state"], "Aborted");
    browser.wait_until("the machine shows Aborted", WAIT, |b| {
        b.exists("#machine-state[data-state=Aborted]")
    });
    assert!(browser.find("#start-job").property("disabled") == json!(true));
    browser.screenshot(&shots.join("4-estop-latched.png"));
    js(&browser, "window.confirm = () => true;");
    browser.find("#reset").click();
    browser.wait_until("the e-stop shows clear", WAIT, |b| {
        b.exists("#estop-state[data-latched=false]")
    });
    // Reset is PackML's Clear then Reset: Aborted, Clearing, Stopped, Resetting, Idle.
    browser.wait_until("the machine shows Idle", WAIT, |b| {
        b.exists("#machine-state[data-state=Idle]")
    });

    // Policies: the bundled policy's first-start evaluation ends before anything else is asked
    // of the registry.
    let bundled = server.wait_evaluated(1, WAIT);
    assert_eq!(bundled["evaluation"]["status"], "done", "{bundled}");
    browser.goto(&format!("{}/#/policies", server.base));
    browser.wait_until("the bundled policy is listed", WAIT, |b| {
        b.exists("tr[data-policy-id='1']")
    });

    // Upload through the form: the bundled `td3` policy file becomes policy 2, as stored.
    let file = concat!(env!("CARGO_MANIFEST_DIR"), "/policies/td3.safetensors");
    browser.find("#policy-file").send_keys(file);
    browser.find("#policy-name").send_keys("td3 from the page");
    browser
        .find("form:has(#policy-file) button[type=submit]")
        .click();
    browser.wait_until("the upload's answer", WAIT, |b| {
        text_of(b, "#policy-answer").contains("Registered policy 2")
    });
    let (_, uploaded) = server.get("/api/policies/2", Some(&server.admin));
    assert_eq!(uploaded["name"], "td3 from the page");
    assert_eq!(
        uploaded["size_bytes"].as_u64().unwrap(),
        std::fs::metadata(file).unwrap().len()
    );
    assert!(browser.exists("tr[data-policy-id='2']"));

    // Activating it after an evaluation below the gate shows the gate's refusal; declining to
    // force keeps things as they were.
    let (status, evaluation) = server.post(
        "/api/policies/2/evaluate",
        Some(&server.admin),
        Some(json!({"episodes": 200})),
    );
    assert_eq!(status, 202, "{evaluation}");
    let evaluated = server.wait_evaluated(2, WAIT);
    assert_eq!(evaluated["evaluation"]["status"], "done", "{evaluated}");
    browser.goto(&format!("{}/#/live", server.base));
    browser.goto(&format!("{}/#/policies", server.base));
    browser.wait_until("policy 2 with its evaluation", WAIT, |b| {
        b.exists("tr[data-policy-id='2']")
    });
    let row = text_of(&browser, "tr[data-policy-id='2']");
    assert!(row.contains("200 episodes (seed 1, cell "), "{row}");
    js(&browser, "window.prompt = () => null;");
    browser
        .find("tr[data-policy-id='2'] button:last-child")
        .click();
    browser.wait_until("the gate's answer", WAIT, |b| {
        text_of(b, "#policy-answer").contains("activation needs")
    });
    let (_, policy) = server.get("/api/policies/2", Some(&server.admin));
    assert_ne!(policy["status"], "active");
    browser.screenshot(&shots.join("5-policy-gate.png"));

    // A run for any cell with a DAgger round, started from the training page: the page sends
    // both settings, the run records cell-scaled demonstrations; it is cancelled before it
    // learns for long.
    browser.goto(&format!("{}/#/training", server.base));
    browser.wait_until("the training form", WAIT, |b| {
        b.exists("#training-any-cell")
    });
    browser.find("#training-record").clear();
    browser.find("#training-record").send_keys("10");
    browser.find("#training-any-cell").click();
    browser.find("#training-dagger").clear();
    browser.find("#training-dagger").send_keys("1");
    browser.find("#training-start").click();
    browser.wait_until("the run's page", WAIT, |b| {
        b.current_url().contains("#/training/")
    });
    let (_, runs) = server.get("/api/training", Some(&server.admin));
    let run = runs["items"][0].clone();
    assert_eq!(run["settings"]["for_any_cell"], true, "{run}");
    assert_eq!(run["settings"]["dagger_rounds"], 1, "{run}");
    let run_id = run["id"].as_i64().unwrap();
    let (status, _) = server.post(
        &format!("/api/training/{run_id}/cancel"),
        Some(&server.admin),
        None,
    );
    assert_eq!(status, 202);
    // The page redraws the run every 2 s, so its status is read in one script.
    browser.wait_until("the page shows the run cancelled", WAIT, |b| {
        js(
            b,
            "return document.querySelector('#training-status')?.textContent ?? '';",
        )
        .as_str()
        .is_some_and(|status| status.contains("cancelled"))
    });
    browser.goto(&format!("{}/#/demonstrations", server.base));
    browser.wait_until("the recorded demonstrations, cell-scaled", WAIT, |b| {
        text_of(b, "#demonstration-list").contains("cell-scaled")
    });

    // A tablet: nothing wider than the window.
    browser.set_window_size(768, 1024);
    browser.goto(&format!("{}/#/live", server.base));
    browser.wait_until("the live page", WAIT, |b| b.exists("#chart-live-errors"));
    let overflow = js(
        &browser,
        "return document.documentElement.scrollWidth - document.documentElement.clientWidth;",
    );
    assert!(
        overflow.as_i64().unwrap() <= 0,
        "wider than a tablet by {overflow} px"
    );
    browser.screenshot(&shots.join("6-tablet.png"));
    browser.set_window_size(1366, 900);

    // A viewer signs in with the form and sees no start, cancel, e-stop or reset button.
    let viewer = server.token("viewer");
    browser.find("#signout").click();
    browser.wait_until("the sign-in form", WAIT, |b| b.exists("#token"));
    browser.find("#token").send_keys(&viewer);
    browser.find("#signin-submit").click();
    browser.wait_until("signed in as viewer", WAIT, |b| {
        text_of(b, "#whoami").contains("viewer")
    });
    browser.wait_until("the live page for a viewer", WAIT, |b| {
        b.exists("#viewer-note")
    });
    for control in [
        "#start-job",
        "#estop",
        "#cancel-job",
        "#stop",
        "#reset",
        "#start-form",
    ] {
        assert!(!browser.exists(control), "a viewer sees {control}");
    }
    browser.goto(&format!("{}/#/policies", server.base));
    browser.wait_until("the policy list for a viewer", WAIT, |b| {
        b.exists("tr[data-policy-id='1']")
    });
    assert!(
        !browser.exists("#policy-file"),
        "a viewer sees the upload form"
    );
    let page_text = text_of(&browser, "#view");
    assert!(!page_text.contains("null"), "{page_text}");
    browser.screenshot(&shots.join("7-viewer.png"));

    // The server goes away: the page says so.
    browser.goto(&format!("{}/#/live", server.base));
    browser.wait_until("the live page with the last job", WAIT, |b| {
        b.exists(&format!("#live-job[data-job-id='{learned_id}']"))
    });
    server.kill9();
    browser.wait_until("the unreachable message", WAIT, |b| {
        text_of(b, "#link-state") == "unreachable"
            && text_of(b, "#banner-text").contains("does not answer")
    });
    browser.screenshot(&shots.join("8-server-unreachable.png"));
    eprintln!("screenshots in {}", shots.display());
}

/// The robot driver's latch on the live page: what, why and since when, jobs refused, the
/// reset offered; a reset while the controller is down shows the service's reason and keeps
/// the latch; with the controller back, the page's reset clears it.
#[test]
fn a_latched_robot_driver_is_shown_and_reset_from_the_dashboard() {
    let Some((browser, shots)) = browser() else {
        return;
    };
    let twin = TwinServer::start(&[]);
    let (gcs, igtl) = (twin.gcs.port(), twin.igtl.port());
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(
        dir.path(),
        &[
            ("CELLD_ROBOT_DRIVER", "gcs"),
            ("CELLD_ROBOT_PORT", &gcs.to_string()),
            ("CELLD_ROBOT_REHEARSAL", "true"),
            ("CELLD_CAMERA_DRIVER", "igtl"),
            ("CELLD_CAMERA_PORT", &igtl.to_string()),
            ("CELLD_ROBOT_ANSWER_TIMEOUT_MS", "2000"),
            ("CELLD_CAMERA_FRAME_TIMEOUT_MS", "300"),
        ],
    );
    browser.set_window_size(1366, 900);
    browser.goto(&server.signin_url.clone().expect("a sign-in link"));
    browser.wait_until("signed in", WAIT, |b| {
        text_of(b, "#whoami").contains("admin")
    });
    browser.goto(&format!("{}/#/live", server.base));
    browser.wait_until("the driver ready", WAIT, |b| {
        b.exists("#driver-state[data-latched=false]")
    });
    assert_eq!(browser.find("#reset").property("disabled"), json!(true));

    // The controller goes away between jobs.
    drop(twin);
    browser.wait_until("the driver latched", WAIT, |b| {
        b.exists("#driver-state[data-latched=true]")
    });
    let shown = text_of(&browser, "#driver-state");
    assert!(shown.contains("controller_dropped"), "{shown}");
    assert!(shown.contains("closed by the controller"), "{shown}");
    assert_eq!(browser.find("#reset").property("disabled"), json!(false));
    assert_eq!(browser.find("#start-job").property("disabled"), json!(true));
    browser.screenshot(&shots.join("9-driver-latched.png"));

    // A reset while it is still down: the page shows why, the latch stays.
    js(&browser, "window.confirm = () => true;");
    browser.find("#reset").click();
    browser.wait_until("the refusal", WAIT, |b| {
        text_of(b, "#banner-text").contains("not ready")
    });
    let (_, cell) = server.get("/api/cell", Some(&server.admin));
    assert!(!cell["driver_latch"].is_null(), "{cell}");
    assert!(browser.exists("#driver-state[data-latched=true]"));

    // The controller is back, its platform where the cell left it (no job moved it): the
    // page's reset clears the latch.
    let _twin = TwinServer::start_on(gcs, igtl, &[]);
    browser.find("#reset").click();
    browser.wait_until("the driver ready again", WAIT, |b| {
        b.exists("#driver-state[data-latched=false]")
    });
    assert_eq!(
        browser.find("#start-job").property("disabled"),
        json!(false)
    );
    browser.screenshot(&shots.join("10-driver-reset.png"));
}
