//! What the machine has and what this process holds: the memory available (Linux
//! `MemAvailable`, less under an address-space limit), the peak resident memory, and refusing
//! before it is made an allocation that cannot fit (an allocation that fails aborts the process
//! without a word). Below everything that allocates much: the BVH, renders, meshes, a training
//! run's budget (`train/memory.rs`).

use anyhow::{bail, Result};

/// Memory the system reports as available (Linux `MemAvailable`), if known; less when the
/// process's address space is limited (`ulimit -v`, RLIMIT_AS): what the limit leaves of it.
pub fn available_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(address_space_left().map_or(kb * 1024, |left| left.min(kb * 1024)))
}

/// What the address-space limit (`ulimit -v`) leaves this process (the limit less its `VmSize`),
/// when there is a limit.
fn address_space_left() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut lim = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut lim) } != 0
            || lim.rlim_cur == libc::RLIM_INFINITY
        {
            return None;
        }
        // `rlim_t` is u64 on Linux, not on every Unix.
        #[allow(clippy::unnecessary_cast)]
        let limit = lim.rlim_cur as u64;
        Some(limit.saturating_sub(status_kb("VmSize:").unwrap_or(0) * 1024))
    }
    #[cfg(not(unix))]
    None
}

/// A `KEY: N kB` line of `/proc/self/status`.
fn status_kb(key: &str) -> Option<u64> {
    let text = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = text.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Refuse, before allocating, `need` bytes that `what` would take when more than the memory
/// available ([`available_bytes`]; where the system does not say, more than a process can
/// address): an allocation that fails aborts the process without a word (`memory allocation
/// of N bytes failed`, exit 134). `fix` says what to change. `need` is an f64 so that a
/// request beyond what u64 counts (`render --scale 1e9`) is refused with its true size, not a
/// wrapped or clamped one.
pub fn check_fits(need: f64, what: &str, fix: &str) -> Result<()> {
    // Without a reading, only what no process can address is refused (as a run's budget check
    // does, `train/memory.rs`).
    let avail = available_bytes().unwrap_or(isize::MAX as u64) as f64;
    if need > avail {
        bail!(
            "{what} would take about {} in memory, and {} are available; {fix}",
            size(need),
            size(avail)
        );
    }
    Ok(())
}

/// Peak resident memory of this process so far (Linux `VmHWM`), if known.
pub fn peak_rss_bytes() -> Option<u64> {
    Some(status_kb("VmHWM:")? * 1024)
}

/// `b` bytes in MB below 1 GB, else in GB.
pub fn size(b: f64) -> String {
    if b < 1e9 {
        format!("{:.1} MB", b / 1e6)
    } else {
        format!("{:.2} GB", b / 1e9)
    }
}
