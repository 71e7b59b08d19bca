//! The process's thread setup for the numerical libraries, done once at start-up.

use std::sync::Once;

/// Sets `RAYON_NUM_THREADS` (to the number of available cores) when it is unset. Without it,
/// candle 0.11 re-reads /proc/cpuinfo on every matmul, which makes a batch-1 step several times
/// slower. Call it at the start of `main`, before any thread is spawned and any candle call;
/// further calls do nothing.
pub fn init_cpu_threads() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        if std::env::var_os("RAYON_NUM_THREADS").is_none() {
            let n = std::thread::available_parallelism().map_or(1, |n| n.get());
            // SAFETY: called once, at start-up, before the program reads the environment from
            // other threads (documented requirement of this function).
            unsafe { std::env::set_var("RAYON_NUM_THREADS", n.to_string()) };
        }
    });
}
