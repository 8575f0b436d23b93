use crate::bundle::GraphKind;

#[derive(Debug, Clone, thiserror::Error)]
pub enum BackendError {
    #[error("{graph}.onnx failed: {message}")]
    Run { graph: GraphKind, message: String },
    #[error("{graph}.onnx returned an unexpected output: {message}")]
    BadOutput { graph: GraphKind, message: String },
    #[error("the inference queue is full")]
    QueueFull,
    #[error(
        "the request cannot finish before its deadline: about {work_secs:.1} s of work, after {ahead_secs:.1} s \
         of work admitted ahead of it"
    )]
    WouldMissDeadline { work_secs: f64, ahead_secs: f64 },
    #[error(
        "about {ahead_secs:.1} s of work is admitted ahead of the request, more than the {max_secs:.1} s a request \
         without a deadline may wait (--max-queue-wait-secs, or its own work when longer)"
    )]
    QueueWaitTooLong { ahead_secs: f64, max_secs: f64 },
    #[error("the request's deadline passed before its graph runs finished")]
    DeadlineExceeded,
    #[error("not enough memory: the requests in progress and the cached scenes in use hold {in_use_mib} of {budget_mib} MiB")]
    MemoryBusy { in_use_mib: u64, budget_mib: u64, ahead_secs: f64 },
    #[error("an estimated {needed_mib} MiB, more than the {budget_mib} MiB a request may have")]
    TooLarge { needed_mib: u64, budget_mib: u64 },
    #[error("the inference thread has stopped")]
    Stopped,
}
