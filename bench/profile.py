"""ONNX Runtime's profiles of renderer runs: kernel time per operator type."""

from __future__ import annotations

import bisect
import json
from pathlib import Path

# Their kernel time is that of the nodes of their subgraphs, which the profile lists too.
CONTAINER_OPS = ("Loop", "If", "Scan")


def kernel_events_by_run(profile: Path) -> list[list[dict]]:
    """An ONNX Runtime profile's node kernel events, container ops left out, grouped by the run
    they belong to, runs in order."""
    events = json.loads(profile.read_text())
    starts = sorted(e["ts"] for e in events if e.get("name") == "model_run")
    runs: list[list[dict]] = [[] for _ in starts]
    for e in events:
        if (
            e.get("cat") == "Node"
            and e["name"].endswith("_kernel_time")
            and e["args"].get("op_name") not in CONTAINER_OPS
            and e["ts"] >= starts[0]
        ):
            runs[bisect.bisect_right(starts, e["ts"]) - 1].append(e)
    return runs


def kernel_shares(by_op_ms: dict) -> dict:
    """Kernel time per op type and the largest shares of it, container ops left out (the run of
    20261201-1702 was profiled before they were: its JSON counts a Loop's time and its body's)."""
    kept = {op: ms for op, ms in by_op_ms.items() if op not in CONTAINER_OPS}
    total = sum(kept.values()) or 1.0
    top = sorted(kept.items(), key=lambda item: -item[1])[:12]
    return {"kernel_ms": total, "by_op_ms": kept, "by_op_share": {op: ms / total for op, ms in top}}
