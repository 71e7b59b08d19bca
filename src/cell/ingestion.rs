//! Camera ingestion as a task of its own: a thread that takes each shot the camera delivers,
//! runs the ingestion core ([`Ingest`]: frame fit, motion compensation, state fusion) on it and
//! answers with the estimate the controller and the supervisor work from.
//!
//! The twin's camera captures inside the twin (it sees the twin's true pose), so the control
//! thread hands each shot over after its move and collects the estimate at its next tick: the
//! fit runs while the control thread waits for the next period, and a job replays exactly as
//! `celld eval` runs it. A networked camera's frames come the same way: the control thread
//! reads them after the move is on target (`cell::drivers`).

use crate::camera::ingest::{Estimate, Ingest, Shot};
use std::sync::mpsc;

#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("camera ingestion has stopped")]
pub struct IngestionStopped;

/// The control thread's side of the ingestion thread. Dropping it ends the thread.
pub struct Ingestion {
    shots: mpsc::SyncSender<Shot>,
    estimates: mpsc::Receiver<Estimate>,
}

impl Ingestion {
    /// Starts the thread. With `cpu`, it keeps to that CPU (the control thread's: the two take
    /// turns, so they never compete for it) at the control thread's priority.
    pub fn spawn(mut ingest: Ingest, cpu: Option<usize>) -> Ingestion {
        let (shots, inbox) = mpsc::sync_channel::<Shot>(1);
        let (outbox, estimates) = mpsc::sync_channel(1);
        std::thread::Builder::new()
            .name("celld-ingest".into())
            .spawn(move || {
                super::cpu::raise_priority();
                never_preempt_on_wakeup();
                if let Some(cpu) = cpu
                    && let Err(error) = super::cpu::pin_current_thread(&[cpu])
                {
                    tracing::warn!(%error, cpu, "camera ingestion could not move to its CPU");
                }
                for shot in inbox {
                    if outbox.send(ingest.take(&shot)).is_err() {
                        return;
                    }
                }
            })
            .expect("spawn the camera ingestion thread");
        Ingestion { shots, estimates }
    }

    /// Hands one shot over; its estimate comes from [`Ingestion::receive`].
    pub fn send(&self, shot: Shot) -> Result<(), IngestionStopped> {
        self.shots.send(shot).map_err(|_| IngestionStopped)
    }

    /// The estimate of the shot sent last, waiting for it if it is not ready.
    pub fn receive(&self) -> Result<Estimate, IngestionStopped> {
        self.estimates.recv().map_err(|_| IngestionStopped)
    }

    /// Hands one shot over and waits for its estimate.
    pub fn take(&self, shot: Shot) -> Result<Estimate, IngestionStopped> {
        self.send(shot)?;
        self.receive()
    }
}

/// Puts the calling thread in `SCHED_BATCH` (Linux): a shot handed over does not preempt the
/// control thread that sent it when the two share a CPU; ingestion runs once the tick is done.
fn never_preempt_on_wakeup() {
    #[cfg(target_os = "linux")]
    {
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: sched_setscheduler reads `param` only; pid 0 is the calling thread.
        if unsafe { libc::sched_setscheduler(0, libc::SCHED_BATCH, &param) } != 0 {
            tracing::warn!(
                error = %std::io::Error::last_os_error(),
                "camera ingestion stays in the normal scheduling class"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::cell::CellConfig;
    use crate::geometry::CellFrames;
    use crate::sim::{AssemblyEnv, EnvOptions, InitialConditions};

    #[test]
    fn the_thread_answers_each_shot_as_inline_ingestion_does() {
        let cell = CellConfig::reference();
        let frames = CellFrames::from_config(&cell);
        let ingestion = Ingestion::spawn(Ingest::new(&cell, &frames), None);
        let mut inline = Ingest::new(&cell, &frames);
        let mut env = AssemblyEnv::new(&cell, EnvOptions::from_cell(&cell));
        env.begin_episode(5, InitialConditions::from_cell(&cell))
            .unwrap();
        for first in [true, false, false] {
            let shot = env.capture_still(first).clone();
            assert_eq!(ingestion.take(shot.clone()), Ok(inline.take(&shot)));
        }
    }

    #[test]
    fn a_stopped_thread_is_an_error_not_a_hang() {
        let (shots, inbox) = mpsc::sync_channel::<Shot>(1);
        let (outbox, estimates) = mpsc::sync_channel::<Estimate>(1);
        drop((inbox, outbox));
        let stopped = Ingestion { shots, estimates };
        assert_eq!(stopped.take(Shot::default()), Err(IngestionStopped));
    }
}
