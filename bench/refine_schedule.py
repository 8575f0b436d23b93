"""Refine's learning-rate schedules side by side: today's back-off (a validation scoring below the
best sends training back to the best weights at a third of the rate) against a cosine rate from
``lr`` to 0 with no going back, from the same banks, seed and budget of steps.

Every training view is banked first (``OUT/banks``, reused by the next schedule and the next
run), then each schedule trains ``--steps`` steps from the base, validating every ``--every``; the
kept step is chosen on the validation views, and the held-out views are scored for the base and
the kept step. One JSON line per schedule.

    .venv/bin/python -m bench.refine_schedule ../shared/data/llff_horns --holdout 8 --steps 300 --every 50
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.train.refine import Recipe, Refinement, default_bundle, keep_freed_memory
from scnerf_export.train.refine_bank import sweep_in_torch
from scnerf_export.train.refine_bundle import base_model
from scnerf_export.train.refine_capture import read_capture, split_views


def cosine(run: Refinement, step: int, steps: int) -> None:
    for group in run.optimiser.param_groups:
        group["lr"] = run.recipe.lr * 0.5 * (1 + math.cos(math.pi * step / steps))


def one_schedule(name: str, capture, split, onnx: OnnxBundle, args) -> dict:
    model, _, _ = base_model(default_bundle())
    run = Refinement(model, capture, split, onnx, Recipe(steps=args.steps, score_every_steps=args.every), args.out)
    start = time.perf_counter()
    run.bank_scored_views()
    while run.pending:
        run.bank_next()
    banked = time.perf_counter() - start
    run.score_base()
    start = time.perf_counter()
    for step in range(args.steps):
        if name == "cosine":
            cosine(run, step, args.steps)
        run.step()
        if run.progress.step % args.every == 0:
            run.validate(go_back=name == "backoff")
    trained = time.perf_counter() - start
    after, p = run.held_out_after(), run.progress
    return {
        "schedule": name,
        "steps": args.steps,
        "best_step": p.best_step,
        "validation": [round(p.initial["psnr"], 3), round(p.best["psnr"], 3)],
        "held_out": [round(p.held_out_before["psnr"], 3), round(after["psnr"], 3)],
        "scorings": [[h["step"], round(h["psnr"], 3), h["lr"]] for h in p.history],
        "banking_s": round(banked, 1),
        "training_s": round(trained, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data", type=Path)
    parser.add_argument("--holdout", type=int)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--every", type=int, default=50)
    parser.add_argument("--schedules", default="backoff,cosine")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("runs/refine-schedule"))
    args = parser.parse_args()
    keep_freed_memory()
    torch.set_num_threads(args.threads)
    capture = read_capture(args.data)
    split = split_views(capture.scene, args.holdout)
    onnx = OnnxBundle(default_bundle(), threads=args.threads, plane_sweep=sweep_in_torch)
    for name in args.schedules.split(","):
        print(json.dumps(one_schedule(name, capture, split, onnx, args)), flush=True)


if __name__ == "__main__":
    main()
