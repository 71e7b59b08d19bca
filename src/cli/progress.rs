//! Progress of long CLI work (training, the report). On a terminal it is a bar; where stderr
//! is not one (a log file, a service manager, CI) the bar draws nothing, so a plain line is
//! written at each tenth of the work instead: a log of a 20-minute run shows it moving.

use std::borrow::Cow;
use std::io::IsTerminal;
use std::sync::atomic::{AtomicU64, Ordering};

use indicatif::{MultiProgress, ProgressBar, ProgressStyle};

/// A bar over `len` units of one stage of work, named `stage` in its plain lines.
pub struct Progress {
    bar: ProgressBar,
    /// Where stderr is not a terminal: the stage's name and the tenths already written.
    plain: Option<(String, Tenths)>,
}

impl Progress {
    /// `template` is indicatif's, for the bar on a terminal.
    pub fn new(len: u64, stage: &str, template: &str) -> Self {
        let bar = ProgressBar::new(len);
        bar.set_style(ProgressStyle::with_template(template).expect("valid template"));
        let plain =
            (!std::io::stderr().is_terminal()).then(|| (stage.to_string(), Tenths::default()));
        Self { bar, plain }
    }

    /// Draws the bar among `multi`'s (stages that run at once on separate threads).
    pub fn within(self, multi: &MultiProgress) -> Self {
        Self {
            bar: multi.add(self.bar),
            plain: self.plain,
        }
    }

    pub fn set_message(&self, message: impl Into<Cow<'static, str>>) {
        self.bar.set_message(message);
    }

    /// Where resumed work starts; no line for the tenths it skips.
    pub fn set_position(&self, done: u64) {
        self.bar.set_position(done);
        if let Some((_, written)) = &self.plain {
            written.newly_completed(done, self.bar.length().unwrap_or(0));
        }
    }

    /// Counts `units` more done; call it after the message that says how they went.
    pub fn inc(&self, units: u64) {
        self.bar.inc(units);
        let Some((stage, written)) = &self.plain else {
            return;
        };
        let (done, len) = (self.bar.position(), self.bar.length().unwrap_or(0));
        if written.newly_completed(done, len) {
            let elapsed_s = self.bar.elapsed().as_secs_f64();
            match self.bar.message() {
                message if message.is_empty() => {
                    eprintln!("{stage}: {done}/{len} after {elapsed_s:.0} s")
                }
                message => eprintln!("{stage}: {done}/{len} after {elapsed_s:.0} s ({message})"),
            }
        }
    }

    pub fn finish_and_clear(&self) {
        self.bar.finish_and_clear();
    }

    /// Leaves the bar where the work stopped.
    pub fn abandon(&self) {
        self.bar.abandon();
    }
}

/// The tenths of the work already written as plain lines (shared by the threads that count).
#[derive(Default)]
struct Tenths(AtomicU64);

impl Tenths {
    /// Whether `done` of `len` units completes a tenth not yet written; marks it written.
    fn newly_completed(&self, done: u64, len: u64) -> bool {
        let tenth = (done.min(len) * 10).checked_div(len).unwrap_or(10);
        tenth > self.0.fetch_max(tenth, Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The units after which a plain line is written when the work goes one unit at a time.
    fn lines_written(len: u64) -> Vec<u64> {
        let written = Tenths::default();
        (1..=len)
            .filter(|&done| written.newly_completed(done, len))
            .collect()
    }

    #[test]
    fn a_line_at_each_tenth_and_the_last_at_the_end() {
        // Hand-computed: 25 units cross a tenth at 3 (1.2 tenths), 5, 8, 10, 13, 15, 18, 20,
        // 23 and 25; 3 units at each unit (3.3, 6.7, 10 tenths).
        assert_eq!(lines_written(25), [3, 5, 8, 10, 13, 15, 18, 20, 23, 25]);
        assert_eq!(lines_written(3), [1, 2, 3]);
        for len in 1..=300 {
            let lines = lines_written(len);
            assert_eq!(lines.len() as u64, len.min(10), "{len} units");
            assert_eq!(lines.last(), Some(&len), "{len} units");
        }
        // Work that jumps writes one line for the tenths it crossed, and none again after.
        let written = Tenths::default();
        assert!(written.newly_completed(7, 20));
        assert!(!written.newly_completed(7, 20));
        assert!(written.newly_completed(20, 20));
        assert!(!written.newly_completed(20, 20));
    }
}
