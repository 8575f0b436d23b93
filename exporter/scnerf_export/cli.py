"""`scnerf-export`: convert-mvsnerf, init-scnerf, export, fixtures, eval, example, experiment, train,
finetune, blend-heads, refine, quantize, reexport, add-guided, split-volume, volume-tail."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from contextlib import contextmanager
from pathlib import Path

from .model.checkpoint import CheckpointError
from .runtime.band import FILLS
from .train.finetune import Recipe


def cmd_convert(args) -> None:
    from .export.bundle import export_bundle
    from .model.checkpoint import load_mvsnerf

    model, provenance = load_mvsnerf(args.ckpt)
    manifest = export_bundle(model, args.out, provenance, args.volume)
    print(f"wrote {args.out} ({manifest.model_id})")


def cmd_init_scnerf(args) -> None:
    from .model.checkpoint import init_scnerf

    print(f"wrote {init_scnerf(args.from_mvsnerf, args.out, seed=args.seed)}")


def cmd_export(args) -> None:
    from .export.bundle import export_bundle
    from .model.checkpoint import load_checkpoint

    model, provenance = load_checkpoint(args.checkpoint)
    if args.metrics:
        provenance["metrics"] = json.loads(args.metrics.read_text())
    manifest = export_bundle(model, args.out, provenance, args.volume)
    print(f"wrote {args.out} ({manifest.model_id})")


def cmd_fixtures(args) -> None:
    from .export.fixtures import write_fixtures

    print(f"wrote {', '.join(map(str, write_fixtures(args.out, variant=args.variant, seed=args.seed)))}")


def cmd_eval(args) -> None:
    from .evaluate.eval import evaluate, split_names, write_json

    if (args.bundle is None) == (args.server is None):
        raise ValueError("eval takes exactly one of --bundle DIR and --server URL")
    summary = evaluate(
        args.bundle,
        args.scene,
        args.format,
        split_names(args.sources),
        split_names(args.targets),
        args.scale,
        args.near,
        args.far,
        args.threads,
        args.chunk,
        args.save_renders,
        args.target_scale,
        args.server,
        args.band,
    )
    if "lpips_unavailable" in summary:
        print(f"LPIPS not computed: {summary['lpips_unavailable']}")
    if args.json:
        write_json(summary, args.json)
        print(f"wrote {args.json}")


def cmd_example(args) -> None:
    from .data.example import write_example

    print(f"wrote {write_example(args.out)}")


def cmd_experiment(args) -> None:
    from .evaluate.experiment import run

    bundles = {}
    for item in args.bundle:
        name, _, path = item.partition("=")
        if not path:
            raise ValueError(f"--bundle takes NAME=DIR, got {item!r}")
        bundles[name] = Path(path)
    print(run(bundles, args.out, args.scenes, args.cache, args.threads))


def cmd_train(args) -> None:
    from .train.from_scratch import preset, train

    last = train(
        preset(args.preset, args.variant),
        args.out,
        resume=args.resume,
        steps=args.steps,
        seed=args.seed,
        cache_dir=args.cache,
        threads=args.threads,
    )
    print(f"checkpoint {last}")


def cmd_finetune(args) -> None:
    from .train.finetune import finetune

    recipe = Recipe(
        steps=args.steps,
        rays=args.rays,
        lr=args.lr,
        pretrained_lr_scale=args.pretrained_lr_scale,
        scenes=args.scenes,
        seed=args.seed,
        validate_every=args.validate_every,
    )
    print(f"checkpoint {finetune(args.init, args.out, args.shared, recipe, args.threads, args.cache)}")


def cmd_blend_heads(args) -> None:
    from .train.blend import blend_heads

    path, alpha = blend_heads(args.init, args.trained, args.out, args.shared, args.cache)
    print(f"checkpoint {path} (alpha {alpha})")


def cmd_refine(args) -> None:
    from .train.refine import Recipe as RefineRecipe
    from .train.refine import keep_freed_memory, refine

    keep_freed_memory()
    recipe = RefineRecipe(
        minutes=args.minutes,
        train=tuple(t.strip() for t in args.train.split(",") if t.strip()),
        lr=args.lr,
        rays=args.rays,
        seed=args.seed,
    )
    try:
        result = refine(
            args.data,
            args.out,
            recipe,
            base=args.base,
            checkpoint=args.checkpoint,
            fmt=args.format,
            downscale=args.downscale,
            max_pixels=args.max_source_pixels,
            holdout=args.holdout,
            targets=split_list(args.targets),
            validation=split_list(args.validation),
            threads=args.threads,
            keep_state=args.keep_state,
            near=args.near,
            far=args.far,
            ignore_distortion=args.ignore_distortion,
            device=args.device,
        )
    except KeyboardInterrupt:
        print("scnerf-export refine: interrupted before the base was scored: nothing written", file=sys.stderr)
        raise SystemExit(130) from None
    record = result.record
    held, checks = record["held_out_psnr"], record["validation_psnr"]
    steps = f"step {record['steps']} of {record['steps_run']}, {record['minutes']:.1f} min"
    print(
        f"wrote {result.out} ({result.model_id}; {steps}): "
        f"held-out PSNR {held['before']:.2f} -> {held['after']:.2f} dB "
        f"(kept on validation PSNR {checks['before']:.2f} -> {checks['after']:.2f} dB)"
    )
    if result.interrupted:
        raise SystemExit(130)


def split_list(value: str | None) -> list[str] | None:
    return [v.strip() for v in value.split(",") if v.strip()] if value else None


def cmd_quantize(args) -> None:
    from .export.precision import compare_bundles, procedural_cases, quantize_bundle

    graphs = tuple(g.strip() for g in args.graphs.split(",") if g.strip())
    manifest = quantize_bundle(args.bundle, args.out, args.precision, graphs=graphs, min_inner=args.min_inner)
    print(f"wrote {args.out} ({manifest.model_id}, {args.precision}: {', '.join(graphs)})")
    if args.compare:
        width, height = (int(x) for x in args.compare_size.lower().split("x"))
        report = compare_bundles(
            args.bundle, args.out, procedural_cases(args.compare, width, height), threads=args.threads
        )
        for row in report["rows"]:
            print(
                f"{row['case']:>22}  fp32 {row['psnr_fp32']:6.2f} dB  {args.precision} {row['psnr_candidate']:6.2f} dB"
                f"  drop {row['psnr_drop']:+.3f} dB  renderer {row['renderer_seconds_fp32']:.2f} s -> "
                f"{row['renderer_seconds_candidate']:.2f} s"
            )
        verdict = "offer" if report["offer"] else "do not offer"
        print(
            f"mean PSNR drop {report['psnr_drop_db']:+.3f} dB, renderer speed-up x{report['renderer_speedup']:.2f}: "
            f"{verdict} ({report['rule']})"
        )
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(report, indent=2, default=float) + "\n")
            print(f"wrote {args.json}")


def cmd_reexport(args) -> None:
    from .export.reexport import reexport_bundle

    manifest = reexport_bundle(args.bundle, args.out)
    diff = manifest.provenance.reexport["renderer_max_abs_difference"]
    print(f"wrote {args.out} ({manifest.model_id}; renderer agrees with {args.bundle} to {diff:.2g})")


def cmd_add_guided(args) -> None:
    from .export.guided import add_guided

    out = args.out or args.bundle
    manifest = add_guided(args.bundle, out, args.checkpoint)
    diff = manifest.provenance.guided_graphs["guide_max_abs_difference_from_renderer"]
    agreement = f"the guide renders what the renderer renders to {diff:.2g}"
    print(f"wrote the guided-sampling graphs into {out} ({manifest.model_id}; {agreement})")


def cmd_split_volume(args) -> None:
    from .export.split_volume import split_volume_bundle

    manifest = split_volume_bundle(args.bundle, args.out, args.volume)
    diff = manifest.provenance.volume_split["volume_max_abs_difference"]
    print(f"wrote {args.out} ({manifest.model_id}; the volume agrees with {args.bundle} to {diff:.2g})")


def cmd_volume_tail(args) -> None:
    from .export.split_volume import leave_volume_tail_to_server

    difference = leave_volume_tail_to_server(args.bundle)
    print(f"rewrote {args.bundle}/volume_net.onnx (the volume agrees with the old graph's to {difference:.2g})")


VOLUME_OPTION = dict(
    choices=["sweep", "slabs", "whole"],
    default="sweep",
    help="how the graphs build the volume: slab by slab of planes from the server's plane sweep (cost_conv + "
    "volume_net, the default and fastest), slab by slab in the graphs (cost_slab + volume_net), or one volume graph",
)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="scnerf-export", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("convert-mvsnerf", help="public MVSNeRF checkpoint -> mvsnerf bundle")
    c.add_argument("--ckpt", required=True, type=Path)
    c.add_argument("--out", required=True, type=Path)
    c.add_argument("--volume", **VOLUME_OPTION)
    c.set_defaults(func=cmd_convert)

    i = sub.add_parser("init-scnerf", help="public MVSNeRF checkpoint -> scnerf checkpoint that renders the same")
    i.add_argument("--from-mvsnerf", required=True, type=Path, help="the public MVSNeRF checkpoint")
    i.add_argument("--out", required=True, type=Path, help="project checkpoint to write")
    i.add_argument("--seed", type=int, default=0, help="draws the rectifiers' attention weights")
    i.set_defaults(func=cmd_init_scnerf)

    e = sub.add_parser("export", help="checkpoint (project or MVSNeRF) -> bundle")
    e.add_argument("--checkpoint", required=True, type=Path)
    e.add_argument("--out", required=True, type=Path)
    e.add_argument("--metrics", type=Path, help="JSON of measured metrics for the manifest's provenance")
    e.add_argument("--volume", **VOLUME_OPTION)
    e.set_defaults(func=cmd_export)

    f = sub.add_parser(
        "fixtures", help="parity fixtures (random small model) in --out and its -slabs and -sweep siblings"
    )
    f.add_argument("--out", required=True, type=Path)
    f.add_argument("--variant", default="scnerf")
    f.add_argument("--seed", type=int, default=7)
    f.set_defaults(func=cmd_fixtures)

    v = sub.add_parser("eval", help="render target views of a scene through ONNX Runtime and score them")
    v.add_argument("--bundle", type=Path, help="render through ONNX Runtime in this process")
    v.add_argument("--server", help="render through the server at this URL instead (e.g. http://127.0.0.1:8080)")
    v.add_argument("--scene", required=True, type=Path)
    v.add_argument("--format", required=True, choices=["dtu", "blender", "llff", "nerfstudio", "colmap"])
    v.add_argument(
        "--sources",
        help="comma-separated view names, the same for every target, or 'fixed' for the "
        "scene's fixed triple (default: per target, the 3 nearest views by camera-centre distance "
        "among those that are not targets)",
    )
    v.add_argument("--targets", help="comma-separated view names (default: the scene's)")
    v.add_argument("--scale", type=float, default=1.0, help="resize every view by this factor")
    v.add_argument(
        "--target-scale",
        type=float,
        default=1.0,
        help="render targets at 1/n size (ground truth box-averaged); sources stay full size",
    )
    v.add_argument("--near", type=float)
    v.add_argument("--far", type=float)
    v.add_argument("--threads", type=int)
    v.add_argument("--chunk", type=int, help="rays per renderer call (default: the server's for the bundle)")
    v.add_argument(
        "--band",
        choices=FILLS,
        default="sources",
        help="with --bundle: the colour of pixels whose surface a source does not see, as the server's --band "
        "(network: the paper's output); a server uses its own",
    )
    v.add_argument("--json", type=Path, help="write the results here")
    v.add_argument("--save-renders", type=Path, help="write rendered PNGs here")
    v.set_defaults(func=cmd_eval)

    x = sub.add_parser("example", help="the committed example request (held-out procedural scene)")
    x.add_argument("--out", required=True, type=Path)
    x.set_defaults(func=cmd_example)

    m = sub.add_parser("experiment", help="bundles side by side on held-out procedural scenes per layout and gap")
    m.add_argument("--bundle", action="append", required=True, help="NAME=DIR, repeatable")
    m.add_argument("--out", required=True, type=Path)
    m.add_argument("--scenes", type=int, default=9, help="held-out scenes (a third per layout)")
    m.add_argument("--cache", type=Path, help="procedural scene cache")
    m.add_argument("--threads", type=int)
    m.set_defaults(func=cmd_experiment)

    t = sub.add_parser("train", help="train on procedural scenes")
    t.add_argument("--variant", required=True, choices=["mvsnerf", "scnerf", "scnerf-geometry", "scnerf-appearance"])
    t.add_argument("--preset", required=True, choices=["cpu-small", "gpu"])
    t.add_argument("--out", required=True, type=Path)
    t.add_argument("--resume", action="store_true")
    t.add_argument("--steps", type=int)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--cache", type=Path, help="procedural scene cache (default OUT/cache)")
    t.add_argument("--threads", type=int)
    t.set_defaults(func=cmd_train)

    defaults = Recipe()
    n = sub.add_parser("finetune", help="train scnerf's heads on a frozen backbone from an init-scnerf checkpoint")
    n.add_argument("--init", required=True, type=Path, help="checkpoint from init-scnerf")
    n.add_argument("--out", required=True, type=Path)
    n.add_argument(
        "--shared",
        type=Path,
        default=Path("../shared"),
        help="folder with data/ (validation scenes: they choose the checkpoint, never train)",
    )
    n.add_argument("--steps", type=int, default=defaults.steps)
    n.add_argument("--rays", type=int, default=defaults.rays, help="rays per step")
    n.add_argument("--lr", type=float, default=defaults.lr, help="learning rate of the rectifiers")
    n.add_argument(
        "--pretrained-lr-scale",
        type=float,
        default=defaults.pretrained_lr_scale,
        help="M2's and M4's learning rate relative to the rectifiers'",
    )
    n.add_argument("--scenes", type=int, default=defaults.scenes, help="procedural training scenes")
    n.add_argument("--validate-every", type=int, default=defaults.validate_every)
    n.add_argument("--seed", type=int, default=defaults.seed)
    n.add_argument("--threads", type=int)
    n.add_argument("--cache", type=Path, help="procedural scenes and ray banks (default OUT/cache); reusable")
    n.set_defaults(func=cmd_finetune)

    b = sub.add_parser(
        "blend-heads", help="finetuned heads moved toward the initialisation, alpha chosen view by view on validation"
    )
    b.add_argument("--init", required=True, type=Path, help="checkpoint from init-scnerf")
    b.add_argument("--trained", required=True, type=Path, help="checkpoint from finetune")
    b.add_argument("--out", required=True, type=Path)
    b.add_argument("--shared", type=Path, default=Path("../shared"), help="folder with data/ (validation scenes)")
    b.add_argument("--cache", required=True, type=Path, help="folder for the validation views' ray banks")
    b.set_defaults(func=cmd_blend_heads)

    add_refine_parser(sub)

    q = sub.add_parser("quantize", help="float32 bundle -> int8 or fp16 bundle (renderer MatMuls), PSNR check")
    q.add_argument("--bundle", required=True, type=Path, help="float32 bundle")
    q.add_argument("--out", required=True, type=Path)
    q.add_argument("--precision", required=True, choices=["int8", "fp16"])
    q.add_argument("--graphs", default="renderer", help="comma-separated: renderer (default), volume")
    q.add_argument("--min-inner", type=int, default=16, help="convert only products with inner size >= this")
    q.add_argument(
        "--compare",
        type=int,
        default=0,
        metavar="N",
        help="render N held-out procedural views through both bundles and report the PSNR drop",
    )
    q.add_argument("--compare-size", default="160x128")
    q.add_argument("--threads", type=int)
    q.add_argument("--json", type=Path, help="write the comparison here")
    q.set_defaults(func=cmd_quantize)

    r = sub.add_parser("reexport", help="exporter 0.1 bundle -> the same model with this exporter's renderer graph")
    r.add_argument("--bundle", required=True, type=Path)
    r.add_argument("--out", required=True, type=Path)
    r.set_defaults(func=cmd_reexport)

    g = sub.add_parser(
        "add-guided", help="a bundle's guided-sampling graphs, from its renderer graph's weights (or its checkpoint)"
    )
    g.add_argument("--bundle", required=True, type=Path)
    g.add_argument("--out", type=Path, help="write a copy with the graphs here (default: into --bundle)")
    g.add_argument("--checkpoint", type=Path, help="export from this checkpoint instead of reading the weights back")
    g.set_defaults(func=cmd_add_guided)

    s = sub.add_parser(
        "split-volume", help="bundle -> the same model with its volume graphs for another build (default: sweep)"
    )
    s.add_argument("--bundle", required=True, type=Path)
    s.add_argument("--out", required=True, type=Path)
    s.add_argument("--volume", choices=["sweep", "slabs"], default="sweep", help="how the new graphs build the volume")
    s.set_defaults(func=cmd_split_volume)

    t = sub.add_parser(
        "volume-tail", help="rewrite a bundle's volume_net.onnx in place to leave G2's last step to the server"
    )
    t.add_argument("--bundle", required=True, type=Path)
    t.set_defaults(func=cmd_volume_tail)
    return p


def add_refine_parser(sub) -> None:
    from .train.refine import DEVICES
    from .train.refine import Recipe as RefineRecipe
    from .train.refine_capture import MAX_SOURCE_PIXELS

    defaults = RefineRecipe()
    r = sub.add_parser(
        "refine",
        help="fine-tune a bundle's network on one capture's views, chosen on validation views -> bundle",
        description="Fine-tune a bundle's renderer (trunk M1 and heads; the encoder and volume graphs stay) on "
        "a capture's own views, each rendered from its 3 nearest training views as the server renders it. "
        "Validation views (taken from the training views) are scored as training goes and choose the step "
        "written as a bundle; held-out views are scored before and after, for the record. Neither is ever "
        "trained on nor a source. Ctrl-C writes the best so far; the same command again resumes. docs/refine.md.",
    )
    r.add_argument("data", type=Path, help="capture folder (COLMAP, nerfstudio, Blender, LLFF, DTU) or transforms file")
    r.add_argument(
        "--out", required=True, type=Path, help="bundle folder to write (its .refine/ holds the state until the end)"
    )
    r.add_argument("--minutes", type=float, default=defaults.minutes, help="time budget, writing included")
    held = r.add_mutually_exclusive_group()
    held.add_argument(
        "--holdout",
        type=int,
        metavar="K",
        help="hold out every K-th view (default: the capture's "
        "own targets, e.g. Blender's val or DTU's test views, else every 8th)",
    )
    held.add_argument("--targets", metavar="NAMES", help="comma-separated names of the views to hold out")
    r.add_argument(
        "--validation",
        metavar="NAMES",
        help="comma-separated names of the training views that choose the kept step, not held out "
        "(default: 1 in 8 of the views left after the hold-out, at least one)",
    )
    r.add_argument(
        "--from", dest="base", type=Path, help="bundle to refine (default $SCNERF_BUNDLE, else bundles/default)"
    )
    r.add_argument(
        "--checkpoint",
        type=Path,
        help="the base bundle's source checkpoint (default: weights read "
        "back from its renderer.onnx); checked against the bundle's renderer either way",
    )
    r.add_argument("--format", choices=["dtu", "blender", "llff", "nerfstudio", "colmap"], help="default: detected")
    r.add_argument(
        "--downscale",
        type=int,
        metavar="N",
        help="read images_N (default: the largest set within --max-source-pixels, as the server picks)",
    )
    r.add_argument("--max-source-pixels", type=int, default=MAX_SOURCE_PIXELS, help="the server's source limit")
    r.add_argument("--near", type=float, help="depth range (default: the capture's files', else from its poses)")
    r.add_argument("--far", type=float)
    r.add_argument(
        "--ignore-distortion",
        action="store_true",
        help="use photos with lens distortion as pinhole (default: undistorted, as the server sends them)",
    )
    r.add_argument("--train", default=",".join(defaults.train), help="what trains: trunk, heads or trunk,heads")
    r.add_argument("--lr", type=float, default=defaults.lr)
    r.add_argument("--rays", type=int, default=defaults.rays, help="rays per step")
    r.add_argument("--seed", type=int, default=defaults.seed)
    r.add_argument("--threads", type=int)
    r.add_argument(
        "--device",
        choices=DEVICES,
        default="auto",
        help="where steps run: auto (default) is cuda when PyTorch sees a GPU, else cpu",
    )
    r.add_argument(
        "--keep-state",
        action="store_true",
        help="keep OUT/.refine (state and ray banks) at the end, so that a rerun with more --minutes goes on",
    )
    r.set_defaults(func=cmd_refine)


@contextmanager
def warnings_as_lines(command: str):
    """Each warning printed as one line of the command's own, like its errors, without Python's
    file, line number and source excerpt, which tell a user nothing."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"scnerf-export {command}: warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():  # puts the display back afterwards
        warnings.showwarning = show
        yield


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        with warnings_as_lines(args.command):
            args.func(args)
    except (CheckpointError, FileNotFoundError, ValueError, KeyError) as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"scnerf-export {args.command}: error: {message}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
