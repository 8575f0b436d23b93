//! The first step of loading the models of `--models DIR`, at start and on every reload: the
//! scan and each new bundle folder's manifest and graph hashes, on a blocking thread and before
//! a deadline (`--models-timeout-secs`), so that no folder's content can hold an async worker
//! (and with it the sockets it serves) or the reload lock for long.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::skips::{Refusals, Skipped, Snapshot};
use super::{duplicate_name, model_name, same_folder, scan};
use crate::backend::MemoryBudget;
use crate::blocking::{self, Cancel};
use crate::bundle::{Bundle, Stop};

/// What to look for below DIR.
pub struct Search {
    pub dir: PathBuf,
    /// The names served already, with their folders: a folder of a served name elsewhere is
    /// skipped (two models of one name), the served folder itself passed over.
    pub served: Vec<(Arc<str>, PathBuf)>,
    /// The memory budget as it stands: a bundle whose graphs would not fit beside what is set
    /// aside is skipped before its graphs are read. None at start: the budget is set aside later.
    pub memory: Option<MemoryBudget>,
    pub refusals: Arc<Refusals>,
    pub timeout: Duration,
}

/// The verified bundles of new folders, and the folders skipped.
#[derive(Default)]
pub struct Candidates {
    pub bundles: Vec<Bundle>,
    pub skipped: Vec<Skipped>,
}

impl Search {
    /// Runs the search on a blocking thread. Past the deadline it stops between two files (or
    /// two chunks of one), keeping what it verified; an abandoned reload stops it the same way.
    pub async fn run(self) -> Candidates {
        let (dir, timeout) = (self.dir.clone(), self.timeout);
        let deadline = Instant::now() + timeout;
        let work = blocking::run(move |cancel| Ok(self.find(deadline, cancel)));
        // The search stops itself at the deadline; this bounds a read that never returns.
        match tokio::time::timeout(timeout + Duration::from_secs(1), work).await {
            Ok(Ok(found)) => found,
            Ok(Err(e)) => Candidates { skipped: vec![Skipped::new(&dir, &e.message())], ..Default::default() },
            Err(_) => Candidates { skipped: vec![Skipped::new(&dir, &past_deadline(timeout))], ..Default::default() },
        }
    }

    fn find(self, deadline: Instant, cancel: &Cancel) -> Candidates {
        let stop = || match (cancel.is_set(), Instant::now() >= deadline) {
            (true, _) => Err("the reload was abandoned".to_string()),
            (false, true) => Err(past_deadline(self.timeout)),
            (false, false) => Ok(()),
        };
        let mut out = Candidates::default();
        let found = match scan::bundle_dirs(&self.dir, &stop) {
            Ok(found) => found,
            Err(reason) => return Candidates { skipped: vec![Skipped::new(&self.dir, &reason)], ..out },
        };
        out.skipped.extend(found.skipped.iter().map(|(dir, reason)| Skipped::new(dir, reason)));
        self.refusals.keep_only(&found.bundles);
        let mut memory = self.memory;
        for dir in found.bundles {
            let name = model_name(&dir);
            let new = out.bundles.iter().map(|b| (model_name(&b.dir), b.dir.clone()));
            let taken =
                self.served.iter().map(|(n, d)| (n.to_string(), d.clone())).chain(new).find(|(n, _)| *n == name);
            let verified = match taken {
                Some((_, first)) if same_folder(&first, &dir) => continue,
                Some((_, first)) => Err(duplicate_name(&name, &first, &dir)),
                None => stop().and_then(|()| self.verify(&dir, memory.as_mut(), &stop)),
            };
            match verified {
                Ok(bundle) => out.bundles.push(bundle),
                Err(reason) => out.skipped.push(Skipped::new(&dir, &reason)),
            }
        }
        out
    }

    /// The bundle of `dir`, verified, when it fits `memory` (which then holds its graphs too).
    /// A refusal for what the folder holds is remembered; one for memory or the deadline is not.
    fn verify(&self, dir: &Path, memory: Option<&mut MemoryBudget>, stop: Stop) -> Result<Bundle, String> {
        if let Some(reason) = self.refusals.recall(dir) {
            return Err(reason);
        }
        let before = Snapshot::of(dir);
        let refused = |reason: String| {
            self.refusals.remember(before.clone(), &reason);
            reason
        };
        let bundle = Bundle::read(dir).map_err(|e| refused(e.message))?;
        let graphs = bundle.graph_bytes();
        if let Some(memory) = memory {
            room_for(graphs, memory)?;
            memory.reserved += graphs;
        }
        bundle.verify(stop).map_err(|e| if stop().is_err() { e } else { refused(e) })?;
        Ok(bundle)
    }
}

/// Refuses graphs of `graphs` bytes that would not fit the memory left beside what is set aside
/// now (sessions hold at least their weights), before any is read or any session made.
pub fn room_for(graphs: u64, memory: &MemoryBudget) -> Result<(), String> {
    match memory.reserved.saturating_add(graphs) < memory.total {
        true => Ok(()),
        false => Err(format!(
            "not enough memory: its graphs ({} MiB) and the {} MiB held at rest exceed the budget ({} MiB)",
            graphs >> 20,
            memory.reserved >> 20,
            memory.total >> 20
        )),
    }
}

fn past_deadline(timeout: Duration) -> String {
    format!("stopped at the models folder's deadline ({} s, --models-timeout-secs)", timeout.as_secs_f64())
}
