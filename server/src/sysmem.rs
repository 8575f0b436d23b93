//! The process's and the machine's memory, read from Linux's `/proc` and cgroup files: resident
//! set now and at its peak, resetting the peak, the memory this process may use at most, and the
//! per-stage probe behind `--memory-probe`. Elsewhere (no `/proc`) every reading is `None`.

use std::collections::BTreeMap;
use std::sync::Mutex;

/// Resident set size of this process, in bytes: now (`VmRSS`) and its peak (`VmHWM`) since the
/// start or the last [`reset_peak`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Resident {
    pub now: u64,
    pub peak: u64,
}

pub fn resident() -> Option<Resident> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    Some(Resident { now: status_kib(&status, "VmRSS:")? * 1024, peak: status_kib(&status, "VmHWM:")? * 1024 })
}

/// Resets the peak (`VmHWM`) to the current resident set: writing 5 to `clear_refs` does only
/// that (proc(5)). False where it cannot be written.
pub fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

fn status_kib(status: &str, field: &str) -> Option<u64> {
    status.lines().find_map(|l| l.strip_prefix(field)?.trim().strip_suffix("kB")?.trim().parse().ok())
}

/// The most memory this process may use, and where that figure comes from: the cgroup's limit
/// (v2 `memory.max`, else v1 `memory.limit_in_bytes`) when there is one below physical memory,
/// else physical memory (`MemTotal`).
pub fn memory_limit() -> Option<(u64, &'static str)> {
    let physical =
        std::fs::read_to_string("/proc/meminfo").ok().and_then(|m| status_kib(&m, "MemTotal:")).map(|k| k * 1024);
    let cgroup = cgroup_limit();
    match (cgroup, physical) {
        (Some(c), Some(p)) if c < p => Some((c, "cgroup")),
        (_, Some(p)) => Some((p, "physical memory")),
        (Some(c), None) => Some((c, "cgroup")),
        (None, None) => None,
    }
}

/// The limit of this process's cgroup; `None` when unlimited (`max`, or v1's huge sentinel).
fn cgroup_limit() -> Option<u64> {
    let paths = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    // v2: one line "0::/path"; v1: "N:memory:/path" (and others).
    let v2 = paths.lines().find_map(|l| l.strip_prefix("0::"));
    let v1 = paths.lines().find_map(|l| l.split(':').nth(2).filter(|_| l.split(':').nth(1) == Some("memory")));
    let candidates = [
        v2.map(|p| format!("/sys/fs/cgroup{p}/memory.max")),
        Some("/sys/fs/cgroup/memory.max".to_string()),
        v1.map(|p| format!("/sys/fs/cgroup/memory{p}/memory.limit_in_bytes")),
        Some("/sys/fs/cgroup/memory/memory.limit_in_bytes".to_string()),
    ];
    candidates.into_iter().flatten().find_map(|path| parse_limit(&std::fs::read_to_string(path).ok()?))
}

/// A cgroup limit file's value; `None` for "max" and for v1's "no limit" (a page-rounded
/// `i64::MAX`).
fn parse_limit(text: &str) -> Option<u64> {
    text.trim().parse::<u64>().ok().filter(|&v| v < 1 << 60)
}

/// Makes large blocks (request bodies, decoded images, tensors) go back to the system when
/// freed. glibc raises its mmap threshold after the first such block is freed, up to 32 MiB, and
/// then serves large blocks from its heaps, where uploads of many sizes beside renders fragment
/// them: in a soak of mixed traffic the resident set went from 280 to ~610 MiB in seven minutes
/// with the adaptive threshold and stayed at 120-240 MiB with it fixed at 128 KiB, renders as
/// fast (docs/results.md, "Soak with mixed traffic"). A no-op outside glibc.
pub fn return_large_blocks() {
    // Blocks from 128 KiB up are mapped on their own, and unmapped when freed.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt sets an allocator parameter; called before the runtime starts its threads.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 128 << 10);
    }
}

/// What a stage did to the process's resident set (bytes): its peak while the stage ran, and the
/// resident set when it ended (what stays held afterwards).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StageMemory {
    /// The largest peak over the stage's runs.
    pub peak: u64,
    /// After the stage's latest run.
    pub after: u64,
}

/// `--memory-probe`: resets the process's peak resident set before each stage (a graph run, or
/// decoding the sources) and reads it after, so that each stage's peak is its own. A diagnostic:
/// the figures are exact only while one request is served at a time (the peak is process-wide),
/// and it overwrites `VmHWM`, so the process's own peak is then meaningless.
#[derive(Debug, Default)]
pub struct MemoryProbe {
    stages: Mutex<BTreeMap<&'static str, StageMemory>>,
}

impl MemoryProbe {
    /// Starts measuring one stage.
    pub fn start(&self) -> ProbeRun<'_> {
        reset_peak();
        ProbeRun { probe: self }
    }

    /// Every stage measured so far, by name.
    pub fn stages(&self) -> Vec<(&'static str, StageMemory)> {
        self.lock().iter().map(|(k, v)| (*k, *v)).collect()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<&'static str, StageMemory>> {
        self.stages.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// One stage being measured; [`ProbeRun::finish`] records it.
pub struct ProbeRun<'a> {
    probe: &'a MemoryProbe,
}

impl ProbeRun<'_> {
    pub fn finish(self, stage: &'static str) {
        let Some(now) = resident() else { return };
        tracing::info!(stage, peak_mib = now.peak >> 20, after_mib = now.now >> 20, "memory probe");
        let mut stages = self.probe.lock();
        let entry = stages.entry(stage).or_default();
        entry.peak = entry.peak.max(now.peak);
        entry.after = now.now;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_resident_set_and_resets_its_peak() {
        let before = resident().expect("Linux /proc/self/status");
        assert!(before.now > 0 && before.peak >= before.now, "{before:?}");
        // 64 MiB touched and freed: the peak grows, a reset brings it back near the current set.
        let block = vec![1u8; 64 << 20];
        std::hint::black_box(&block);
        drop(block);
        let grown = resident().unwrap();
        assert!(grown.peak >= before.now + (60 << 20), "{grown:?}");
        assert!(reset_peak());
        let reset = resident().unwrap();
        assert!(reset.peak < grown.peak, "{reset:?} after {grown:?}");
    }

    #[test]
    fn limit_parsing() {
        assert_eq!(parse_limit("max\n"), None);
        assert_eq!(parse_limit("9223372036854771712\n"), None);
        assert_eq!(parse_limit("4294967296\n"), Some(4 << 30));
        let (limit, _) = memory_limit().expect("a limit from /proc/meminfo at least");
        assert!(limit > 64 << 20);
    }
}
