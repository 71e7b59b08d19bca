//! Error messages as people read them: without backtraces. candle's errors carry the backtrace
//! captured where they arose inside their `Display` text when `RUST_BACKTRACE` (or
//! `RUST_LIB_BACKTRACE`) is set, and anyhow's `{:?}` prints one too; neither belongs in an HTTP
//! body, a stored error or the CLI's message, where it says nothing the operator can act on
//! and shows the service's source paths. The log keeps whatever the code logs.

/// `text` with every backtrace left out: the frame lines (`  12: symbol`), their locations
/// (`      at src/file.rs:1:2`), and the `stack backtrace:` headers and notes around them. The
/// message's own lines stay, in order, before and after.
pub fn without_backtrace(text: &str) -> String {
    let mut kept: Vec<&str> = Vec::new();
    let mut in_frames = false;
    for line in text.lines() {
        let trimmed = line.trim_start();
        let header = matches!(
            trimmed.to_ascii_lowercase().as_str(),
            "stack backtrace:" | "backtrace:"
        );
        let frame = line.len() > trimmed.len()
            && trimmed.split_once(':').is_some_and(|(number, _)| {
                !number.is_empty() && number.bytes().all(|b| b.is_ascii_digit())
            });
        let location = in_frames && trimmed.starts_with("at ");
        let note = in_frames && trimmed.starts_with("note: Some details are omitted");
        // A backtrace's text ends with a line break of its own.
        let blank = in_frames && trimmed.is_empty();
        if header || frame || location || note || blank {
            in_frames = true;
            continue;
        }
        in_frames = false;
        kept.push(line);
    }
    kept.join("\n").trim_end().to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A backtrace as std writes one, inside a message with text before and after it.
    #[test]
    fn a_backtrace_is_left_out_and_the_message_kept() {
        let text = "training: the loss is NaN\n   0: candle_core::error::Error::bt\n             \
                    at /home/u/.cargo/registry/src/candle-core/src/error.rs:260:25\n  11: \
                    assembly_cell::learning::bc::train\n             at src/learning/bc.rs:99:5\n\
                    context after";
        assert_eq!(
            without_backtrace(text),
            "training: the loss is NaN\ncontext after"
        );
        let anyhow_debug = "bad file\n\nCaused by:\n    missing tensor\n\nStack backtrace:\n   \
                            0: std::backtrace::Backtrace::capture\n             at src/main.rs:1:1";
        assert_eq!(
            without_backtrace(anyhow_debug),
            "bad file\n\nCaused by:\n    missing tensor"
        );
    }

    #[test]
    fn a_message_without_a_backtrace_is_unchanged() {
        for text in [
            "episode 3, step 7: state[2] = 1e308 is beyond 2000 mm",
            "line 1: expected `,` at line 1 column 5",
            "a: b\n  indented line: with a colon",
        ] {
            assert_eq!(without_backtrace(text), text);
        }
    }

    /// A real backtrace, captured here, comes out.
    #[test]
    fn a_captured_backtrace_is_left_out() {
        let backtrace = std::backtrace::Backtrace::force_capture();
        let text = format!("outer\n{backtrace}\ninner");
        let plain = without_backtrace(&text);
        assert_eq!(plain, "outer\ninner", "{plain}");
    }
}
