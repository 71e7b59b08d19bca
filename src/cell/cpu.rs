//! A CPU of its own for the control thread. Everything else in the service (HTTP workers,
//! SQLite, evaluations, training) runs on the other CPUs, so a burst of requests can take
//! neither the control step's core nor its caches. Threads inherit their creator's CPU set, so
//! the process restricts itself before it starts any thread and the control thread then moves
//! to its own CPU. The threads' priorities (nice values) are set here too: the control and
//! ingestion threads ahead of the rest, background evaluations and training behind it.

pub use crate::config::service::ControlCpu;

/// Where the threads go.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CpuPlan {
    /// The control thread's CPU.
    pub control: usize,
    /// Every other thread's CPUs.
    pub others: Vec<usize>,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CpuPlanError {
    #[error("control.cpu = {cpu}, but this process may use only CPUs {available:?}")]
    NotAvailable { cpu: usize, available: Vec<usize> },
    #[error(
        "control.cpu = {cpu}, but that is the only CPU this process may use: nothing would be left for the rest of the service (use auto or off)"
    )]
    OnlyCpu { cpu: usize },
}

/// `auto` isolates a CPU whenever there is one to spare. On two CPUs that halves what HTTP,
/// SQLite, evaluations and training get, but the control step's timing comes first: on this
/// project's 2-core machine, on a busy day, the latency goals held only with the control thread
/// on a CPU of its own; on a quiet day they held either way (docs/service.md, Figures, runs
/// 10–22). `off` gives every thread every CPU.
pub const AUTO_FROM_CPUS: usize = 2;

/// The placement for `choice` given the CPUs the process may use; `None` when every thread
/// stays anywhere (`off`, or `auto` with a single CPU).
pub fn plan(available: &[usize], choice: ControlCpu) -> Result<Option<CpuPlan>, CpuPlanError> {
    let control = match choice {
        ControlCpu::Off => return Ok(None),
        ControlCpu::Auto => match available.iter().max() {
            Some(&last) if available.len() >= AUTO_FROM_CPUS => last,
            _ => return Ok(None),
        },
        ControlCpu::Cpu(cpu) if !available.contains(&cpu) => {
            return Err(CpuPlanError::NotAvailable {
                cpu,
                available: available.to_vec(),
            });
        }
        ControlCpu::Cpu(cpu) if available.len() < 2 => return Err(CpuPlanError::OnlyCpu { cpu }),
        ControlCpu::Cpu(cpu) => cpu,
    };
    Ok(Some(CpuPlan {
        control,
        others: available
            .iter()
            .copied()
            .filter(|&c| c != control)
            .collect(),
    }))
}

/// The CPUs the calling thread may run on.
pub fn available() -> std::io::Result<Vec<usize>> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `set` is a plain bit array that sched_getaffinity fills; the size passed is its
        // own.
        unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok((0..libc::CPU_SETSIZE as usize)
                .filter(|&cpu| libc::CPU_ISSET(cpu, &set))
                .collect())
        }
    }
    #[cfg(not(target_os = "linux"))]
    Ok((0..std::thread::available_parallelism().map_or(1, |n| n.get())).collect())
}

/// Keeps the calling thread (and the threads it starts from now on) on `cpus`. A no-op
/// outside Linux.
pub fn pin_current_thread(cpus: &[usize]) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `set` is a plain bit array built with the libc helpers; sched_setaffinity only
        // reads it, for the calling thread (pid 0).
        unsafe {
            let mut set: libc::cpu_set_t = std::mem::zeroed();
            for &cpu in cpus {
                libc::CPU_SET(cpu, &mut set);
            }
            if libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set) != 0 {
                return Err(std::io::Error::last_os_error());
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = cpus;
    Ok(())
}

/// Asks the OS to run the control thread ahead of the HTTP workers and the storage writer
/// (nice −10), so a burst of requests cannot delay a step. Needs CAP_SYS_NICE (the systemd unit
/// grants it); without it the thread runs at normal priority and says so.
pub(crate) fn raise_priority() {
    if let Err(error) = set_thread_nice(-10) {
        tracing::warn!(%error, "the control thread runs at normal priority (no CAP_SYS_NICE)");
    }
}

/// Runs the calling thread behind everything else (nice 10): background evaluations and
/// training, which must not take time from a running job.
pub fn lower_priority() {
    if let Err(error) = set_thread_nice(10) {
        tracing::warn!(%error, "could not lower a background thread's priority");
    }
}

/// Sets the calling thread's nice value (Linux; elsewhere a no-op).
fn set_thread_nice(nice: i32) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: setpriority only reads its integer arguments; on Linux, PRIO_PROCESS with
        // who = 0 applies to the calling thread alone.
        if unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, nice) } != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[test]
    fn auto_takes_the_last_cpu_when_there_is_another_for_the_rest() {
        assert_eq!(
            plan(&[0, 1, 2, 3], ControlCpu::Auto).unwrap(),
            Some(CpuPlan {
                control: 3,
                others: vec![0, 1, 2]
            })
        );
        assert_eq!(
            plan(&[2, 5, 7, 8, 9], ControlCpu::Auto)
                .unwrap()
                .unwrap()
                .others,
            vec![2, 5, 7, 8]
        );
        assert_eq!(
            plan(&[0, 1], ControlCpu::Auto).unwrap(),
            Some(CpuPlan {
                control: 1,
                others: vec![0]
            })
        );
        assert_eq!(plan(&[3], ControlCpu::Auto).unwrap(), None);
        assert_eq!(plan(&[0, 1, 2, 3], ControlCpu::Off).unwrap(), None);
    }

    #[test]
    fn a_named_cpu_must_be_available_and_not_the_only_one() {
        assert_eq!(
            plan(&[0, 1, 2], ControlCpu::Cpu(0)).unwrap(),
            Some(CpuPlan {
                control: 0,
                others: vec![1, 2]
            })
        );
        assert_eq!(
            plan(&[0, 1], ControlCpu::Cpu(4)),
            Err(CpuPlanError::NotAvailable {
                cpu: 4,
                available: vec![0, 1]
            })
        );
        assert_eq!(
            plan(&[1], ControlCpu::Cpu(1)),
            Err(CpuPlanError::OnlyCpu { cpu: 1 })
        );
    }

    #[test]
    fn settings_text_round_trips() {
        for choice in [ControlCpu::Auto, ControlCpu::Off, ControlCpu::Cpu(3)] {
            assert_eq!(choice.to_string().parse::<ControlCpu>(), Ok(choice));
        }
        assert!("fast".parse::<ControlCpu>().unwrap_err().contains("fast"));
        #[derive(Deserialize)]
        struct Holder {
            cpu: ControlCpu,
        }
        let number: Holder = toml::from_str("cpu = 2").unwrap();
        assert_eq!(number.cpu, ControlCpu::Cpu(2));
        let text: Holder = toml::from_str("cpu = \"off\"").unwrap();
        assert_eq!(text.cpu, ControlCpu::Off);
    }

    /// The calling thread can be moved onto one of its CPUs and back (the kernel agrees).
    #[cfg(target_os = "linux")]
    #[test]
    fn pinning_moves_the_thread() {
        std::thread::spawn(|| {
            let all = available().unwrap();
            pin_current_thread(&all[..1]).unwrap();
            assert_eq!(available().unwrap(), all[..1].to_vec());
            pin_current_thread(&all).unwrap();
            assert_eq!(available().unwrap(), all);
        })
        .join()
        .unwrap();
    }
}
