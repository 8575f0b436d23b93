#!/usr/bin/env python3
"""Eight concurrent renders with 800x800 sources against the real server, under its memory budget.

    PYTHONPATH=exporter:. .venv/bin/python scripts/memory-concurrency.py \\
        --bundle BUNDLE [--memory-budget-mb N] [--concurrent 8] [--size 800x800]

Starts ``target/release/scnerf-server`` on BUNDLE (a paper-size bundle: the converted public
MVSNeRF one, split by ``scnerf-export split-volume`` to build its volume slab by slab, or not),
sends CONCURRENT multipart renders of the lego triple (r_6, r_43, r_33 -> r_28, 80x64 target, from
../shared/data) at once, and checks that every response is 200, 503 (with
Retry-After) or 422; the server is alive afterwards; its peak resident set (VmHWM) stays within
the budget. Prints one JSON line per response and a summary; exits 1 when a check fails.
tests/tests/memory_admission.rs is the same check at a size that fits CI.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.memory import LEGO, process_memory, request_for, request_status
from scnerf_client import Client
from scnerf_export.serving import ServerProcess, find_server_binary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bundle", required=True, type=Path)
    parser.add_argument("--memory-budget-mb", type=int, default=None, help="default: the server's own")
    parser.add_argument("--concurrent", type=int, default=8)
    parser.add_argument("--size", default="800x800")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--server-bin", default=None)
    args = parser.parse_args(argv)
    size = tuple(int(v) for v in args.size.split("x"))
    request = request_for(LEGO, size, (80, 64))
    extra = ["--request-timeout-secs", "7200"]
    if args.memory_budget_mb:
        extra += ["--memory-budget-mb", str(args.memory_budget_mb)]
    server = ServerProcess(find_server_binary(args.server_bin), args.bundle, args.threads, tuple(extra))
    try:
        metrics = server.client.metrics()
        budget = next(
            int(line.split()[1]) for line in metrics.splitlines() if line.startswith("scnerf_memory_budget_bytes")
        )
        rest = process_memory(server.proc.pid)
        print(json.dumps({"budget_mib": budget >> 20, "at_rest": rest}), flush=True)

        client = Client(server.url, max_retries=0)

        def one(i: int) -> dict:
            start = time.perf_counter()
            status, error, retry_after = request_status(client, request)
            out = {"request": i, "status": status, "seconds": round(time.perf_counter() - start, 1)}
            if status != 200:
                out["retry_after"] = retry_after
                out["error"] = error[:240]
            print(json.dumps(out), flush=True)
            return out

        with ThreadPoolExecutor(args.concurrent) as pool:
            results = list(pool.map(one, range(args.concurrent)))
        alive = server.proc.poll() is None
        peak = process_memory(server.proc.pid) if alive else None
    finally:
        server.stop()
    statuses = [r["status"] for r in results]
    failures = []
    if any(s not in (200, 503, 422) for s in statuses):
        failures.append(f"statuses {statuses}")
    if any(r["status"] == 503 and not r.get("retry_after") for r in results):
        failures.append("a 503 without Retry-After")
    if not alive:
        failures.append("the server died")
    elif peak["hwm_mib"] > budget / (1 << 20):
        failures.append(f"peak {peak['hwm_mib']} MiB above the budget {budget >> 20} MiB")
    summary = {
        "size": args.size,
        "concurrent": args.concurrent,
        "statuses": {s: statuses.count(s) for s in sorted(set(statuses))},
        "budget_mib": budget >> 20,
        "peak_mib": peak and peak["hwm_mib"],
        "failures": failures,
    }
    print(json.dumps(summary), flush=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
