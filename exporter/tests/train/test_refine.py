"""`scnerf-export refine` (scnerf_export.train.refine*) on a tiny procedural capture written as a
nerfstudio folder, refining the committed parity-fixture bundle (its weights are
``random_model(small_config(), 7)``, which ``base_model`` checks against its renderer graph).

What is checked: the capture's format, image set and split (validation and held-out views are
disjoint and never sources; a capture too small is refused), the banked rays shade as the renderer
renders, steps on the training views make them score better, validation and held-out views never
reach the optimiser (instrumented: no encoding for a training ray sees them, every step's rays are
training rays, their poisoned pixels never make a gradient), held-out views never reach the
selection (instrumented: scored only for the base and the kept step; the kept step is the best
validation scoring), a resumed run continues exactly as an uninterrupted one, Ctrl-C writes the
best step's bundle and the same command resumes (the bundle's writing stubbed: fast), the device
flag, and, end to end on a budget of steps (slow: it exports the refined renderer twice), the
same with the bundles written and served.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from scnerf_export import cli
from scnerf_export.cameras import target_rays
from scnerf_export.config import small_config
from scnerf_export.data.depth_range import from_poses
from scnerf_export.data.procedural import make_scene
from scnerf_export.data.scene import SceneData, View
from scnerf_export.export.manifest import BAND_RULES, Manifest
from scnerf_export.model.checkpoint import save_checkpoint
from scnerf_export.rigs import random_model
from scnerf_export.runtime.onnx_pipeline import OnnxBundle
from scnerf_export.runtime.reference import encode_scene, render_rays
from scnerf_export.train import refine as refine_module
from scnerf_export.train.refine import Recipe, RefineError, Refinement, refine, snapshot
from scnerf_export.train.refine_bank import Encoded, bank_view, composite, render_raw, score_colours, shade
from scnerf_export.train.refine_bundle import base_model
from scnerf_export.train.refine_capture import (
    CaptureError,
    ImageSet,
    detect_format,
    fit_to_limit,
    pick_image_set,
    read_capture,
    split_views,
    spread_order,
    write_procedural_capture,
)

from conftest import REPO

PARITY_BUNDLE = REPO / "tests" / "fixtures" / "parity" / "bundle"
DATASETS = REPO / "tests" / "fixtures" / "datasets"
WIDTH, HEIGHT = 48, 32
# Small steps and scorings, no time kept back for writing: a test's budget is seconds.
QUICK = Recipe(rays=64, rays_per_view=512, scored_rays=512, min_scored_rays=128, score_every_s=2.0, lr=5e-4)
# A budget of steps, validated every 4: the same run on any machine, however loaded.
COUNTED = replace(QUICK, minutes=30.0, write_reserve_s=0.0, steps=16, score_every_steps=4)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread: on a shared 2-core machine, two threads of small products wait on each
    other (measured here: 25 steps in 22 s with 2 threads beside another job, 1.3 s with one)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    return write_procedural_capture(tmp_path_factory.mktemp("capture") / "c", views=9, width=WIDTH, height=HEIGHT)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """The parity bundle and the checkpoint of its weights."""
    checkpoint = tmp_path_factory.mktemp("base") / "parity.pt"
    save_checkpoint(checkpoint, random_model(small_config(), 7), {})
    return PARITY_BUNDLE, checkpoint


@pytest.fixture(scope="module")
def loaded(capture_dir, base):
    """The capture (every 3rd view held out: v0, v3, v6; v5 validates) and the base network."""
    capture = read_capture(capture_dir)
    split = split_views(capture.scene, holdout=3)
    model, manifest, about = base_model(*base)
    return capture, split, model, OnnxBundle(base[0], threads=1)


def scene_of(count: int) -> SceneData:
    views = make_scene(3, "object", n_views=count, width=16, height=16).views
    named = {f"v{i}": View(f"v{i}", v.image, v.camera) for i, v in enumerate(views)}
    return SceneData(named, 2.0, 6.0, (0.0, 0.0, 0.0), None, None)


# ----------------------------------------------------------------------------------------- capture


@pytest.mark.parametrize("fmt", ["blender", "colmap", "dtu", "llff", "nerfstudio"])
def test_formats_are_detected_as_the_rust_readers_detect_them(fmt):
    assert detect_format(DATASETS / fmt) == fmt


def test_a_binary_colmap_model_is_detected_as_colmap():
    assert detect_format(DATASETS / "colmap_binary") == "colmap"


def test_the_image_set_is_the_largest_within_the_source_limit():
    sets = [ImageSet(1, 4032, 3024), ImageSet(4, 1008, 756), ImageSet(8, 504, 378)]
    assert pick_image_set(sets, None, 1 << 20).factor == 4
    assert pick_image_set(sets, None, 1000).factor == 8  # none fits: the smallest
    assert pick_image_set(sets, 1, 1 << 20).factor == 1
    with pytest.raises(CaptureError, match="no images_2 folder"):
        pick_image_set(sets, 2, 1 << 20)


def test_views_over_the_limit_shrink_as_the_server_shrinks_them():
    scene = scene_of(5)
    assert fit_to_limit(scene, 16 * 16) is None
    fit_to_limit(scene, 100)  # sqrt(100/256) = 0.625 of 16, rounded down
    assert {(v.camera.width, v.camera.height, v.image.shape[:2]) for v in scene.views.values()} == {(10, 10, (10, 10))}


def test_a_capture_without_a_depth_range_takes_its_poses_and_the_flags_win(capture_dir, tmp_path):
    """An instant-ngp or nerfstudio file carries no near/far: refine reads the range the server
    derives from the poses (data/depth_range.py), and --near/--far override it."""
    bare = tmp_path / "bare"
    shutil.copytree(capture_dir, bare)
    transforms = json.loads((bare / "transforms.json").read_text())
    near, far = transforms.pop("near"), transforms.pop("far")
    (bare / "transforms.json").write_text(json.dumps(transforms))
    scene = read_capture(bare).scene
    assert 0 < scene.near < near and far < scene.far  # the procedural object's range, with margins
    assert (scene.near, scene.far) == pytest.approx(from_poses([v.camera for v in scene.views.values()]))
    flagged = read_capture(bare, near=1.5, far=7.0).scene
    assert (flagged.near, flagged.far) == (1.5, 7.0)


def test_validation_and_held_out_views_are_disjoint_and_never_sources():
    scene = scene_of(25)
    split = split_views(scene, holdout=5)
    assert split.held_out == ["v0", "v5", "v10", "v15", "v20"]
    assert split.validation == ["v7", "v19"]  # 1 in 8 of the 20 left, spaced through them
    assert set(split.training) == set(scene.views) - set(split.held_out) - set(split.validation)
    for name, sources in split.sources.items():
        assert len(sources) == 3 and name not in sources and set(sources) <= set(split.training)
    assert sorted(spread_order(scene, split.training)) == sorted(split.training)


def test_one_view_validates_at_least_and_the_flag_names_them():
    assert split_views(scene_of(9), holdout=3).validation == ["v5"]
    split = split_views(scene_of(9), holdout=3, validation=["v8", "v1", "v8"])
    assert split.validation == ["v8", "v1"] and not {"v8", "v1"} & set(split.training)
    with pytest.raises(CaptureError, match="--validation: v3 held out"):
        split_views(scene_of(9), holdout=3, validation=["v3"])
    with pytest.raises(CaptureError, match="--validation: v99 not in the capture"):
        split_views(scene_of(9), holdout=3, validation=["v99"])


def test_a_capture_too_small_is_refused():
    with pytest.raises(CaptureError, match="the capture has 5 views; refine needs at least 6"):
        split_views(scene_of(5))
    with pytest.raises(
        CaptureError, match="no views left to train on: holding out 3 and validating on 1 of 7 views leaves 3"
    ):
        split_views(scene_of(7), targets=["v0", "v1", "v2"])


def test_the_command_refuses_a_capture_too_small(tmp_path, capsys):
    folder = write_procedural_capture(tmp_path / "five", views=5, width=16, height=16)
    assert cli.main(["refine", str(folder), "--out", str(tmp_path / "out")]) == 2
    assert "the capture has 5 views; refine needs at least 6" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_device_flag(monkeypatch):
    refine_args = ["refine", "capture", "--out", "out"]
    assert cli.parser().parse_args(refine_args).device == "auto"
    assert cli.parser().parse_args([*refine_args, "--device", "cpu"]).device == "cpu"
    with pytest.raises(SystemExit):
        cli.parser().parse_args([*refine_args, "--device", "tpu"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert refine_module.resolve_device("auto") == torch.device("cuda")
    assert refine_module.resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert refine_module.resolve_device("auto") == torch.device("cpu")
    with pytest.raises(RefineError, match="--device cuda: PyTorch sees no CUDA GPU"):
        refine_module.resolve_device("cuda")


# ------------------------------------------------------------------------------------------- banks


def test_banked_rays_shade_as_the_renderer_renders(loaded):
    capture, split, model, _ = loaded
    scene = capture.scene
    sources = [scene.views[s] for s in split.sources["v1"]]
    encoded = encode_scene(model, np.stack([v.image for v in sources]), [v.camera for v in sources], 2.0, 6.0)
    pick = np.arange(0, WIDTH * HEIGHT, 7)
    bank = bank_view(model.renderer, Encoded(**encoded.__dict__), scene.views["v1"], pick, 2.0, 6.0, (0, 0, 0), 0)
    origins, directions = target_rays(scene.views["v1"].camera)
    with torch.no_grad():
        rgb, _, opacity = render_rays(model, encoded, origins[pick], directions[pick], 2.0, 6.0, (2.0, 6.0), 512)
        banked = shade(model.renderer, bank, torch.arange(len(pick))).numpy()
    # The bank stores point and appearance features as float16.
    assert np.abs(banked - rgb).max() < 2e-3 and opacity.std() > 0.01


# ---------------------------------------------------------------------------------------- training


def fresh_run(loaded, work: Path, recipe: Recipe = QUICK) -> Refinement:
    capture, split, model, onnx = loaded
    return Refinement(copy.deepcopy(model), capture, split, onnx, recipe, work)


def banked(run: Refinement) -> Refinement:
    run.bank_scored_views()
    while run.pending:
        run.bank_next()
    return run


def training_views_psnr(run: Refinement) -> float:
    rgb, _, opacity = render_raw(run.renderer, run.train_bank)
    return score_colours(run.train_bank, composite(run.train_bank, rgb, opacity), run.banked)["psnr"]


def test_steps_make_the_training_views_score_better(loaded, tmp_path):
    run = banked(fresh_run(loaded, tmp_path))
    before = training_views_psnr(run)
    for _ in range(25):
        run.step()
    after = training_views_psnr(run)
    assert after > before + 0.5, (before, after)


def test_validation_and_held_out_views_never_reach_the_optimiser(loaded, tmp_path, monkeypatch):
    capture, split, model, onnx = loaded
    poisoned = copy.deepcopy(capture)
    for name in split.held_out + split.validation:  # their pixels in a source or a step would make NaN
        poisoned.scene.views[name].image[:] = np.nan
    encodes = []
    original_encode = onnx.encode_scene

    def encode(images, *args):
        encodes.append(bool(np.isfinite(images).all()))
        return original_encode(images, *args)

    monkeypatch.setattr(onnx, "encode_scene", encode)
    drawn = []
    original_shade = refine_module.shade

    def recording_shade(renderer, bank, idx):
        drawn.append((bank, idx.clone()))
        return original_shade(renderer, bank, idx)

    monkeypatch.setattr(refine_module, "shade", recording_shade)
    run = banked(Refinement(copy.deepcopy(model), poisoned, split, onnx, QUICK, tmp_path))
    gradients = []

    def finite_gradients(optimiser, args, kwargs):
        # W_k's bias never has one: a shift of every key by the same vector leaves the softmax as it is.
        grads = [p.grad for p in run.params.values() if p.grad is not None]
        gradients.append(len(grads) > len(run.params) // 2 and all(bool(torch.isfinite(g).all()) for g in grads))

    run.optimiser.register_step_pre_hook(finite_gradients)
    losses = [run.step() for _ in range(10)]

    assert encodes and all(encodes), "an encoding saw a validation or held-out view"
    assert set(run.banked) == set(split.training)
    for bank, idx in drawn:
        assert bank is run.train_bank
        assert {run.banked[i] for i in bank.view[idx].tolist()} <= set(split.training)
    assert len(gradients) == 10 and all(gradients) and all(math.isfinite(x) for x in losses)
    # The poison is there: the scored views' pixels are NaN.
    assert math.isnan(run.validate()["psnr"]) and math.isnan(run.score_held_out("when_dark")["psnr"])


def test_the_base_scores_by_its_band_rule_and_a_step_by_the_rule_that_serves_it_best(loaded, tmp_path):
    run = banked(fresh_run(loaded, tmp_path))
    base = run.validate()
    assert base["band"] == run.onnx.manifest.band and base["psnr"] == base["psnr_by_band"][base["band"]]
    run.step()
    step = run.validate()
    assert set(step["psnr_by_band"]) == set(BAND_RULES)
    assert step["psnr"] == max(step["psnr_by_band"].values()) == step["psnr_by_band"][step["band"]]
    assert f"validation {step['psnr']:.2f} dB (best " in refine_module.status(run)  # the progress line


def test_held_out_views_never_reach_the_selection(loaded, tmp_path, monkeypatch):
    """The held-out views are scored for the base and the kept step, nothing between; the kept step
    and its band rule are the validation scorings' best, whatever the held-out views score (NaN
    here: their pixels are poisoned, so a comparison with them would never pick a step)."""
    capture, split, model, onnx = loaded
    poisoned = copy.deepcopy(capture)
    for name in split.held_out:
        poisoned.scene.views[name].image[:] = np.nan
    run = Refinement(copy.deepcopy(model), poisoned, split, onnx, COUNTED, tmp_path)
    scored = []
    original_score = refine_module.score

    def recording_score(renderer, bank, names, sources, rules=BAND_RULES):
        scored.append((tuple(names), run.progress.step, len(bank)))
        return original_score(renderer, bank, names, sources, rules)

    monkeypatch.setattr(refine_module, "score", recording_score)
    refine_module.run_budget(run, {"base_model_id": "base"})
    after = run.held_out_after()

    p, held, validation = run.progress, tuple(split.held_out), tuple(split.validation)
    assert p.step == 16 and {h["step"] for h in p.history} == {0, 4, 8, 12, 16}
    assert [s[:2] for s in scored if s[0] == held] == [(held, 0)] + ([(held, 16)] if p.best_step else [])
    assert all(s[0] == validation for s in scored if s[0] != held) and len(scored) == len(p.history) + 1 + (
        p.best_step > 0
    )
    assert {s[2] for s in scored if s[0] == held} == {len(run.held_out.bank)}
    history = [h["psnr"] for h in p.history]
    assert all(math.isfinite(x) for x in history) and len(set(history)) > 1
    assert p.best_step > 0 and p.history[history.index(max(history))]["step"] == p.best_step
    assert p.best["band"] == p.history[history.index(max(history))]["band"]
    assert math.isnan(p.held_out_before["psnr"]) and math.isnan(after["psnr"]) and after["band"] == p.best["band"]


def test_a_scoring_below_the_best_goes_back_to_the_best_at_a_smaller_learning_rate(loaded, tmp_path):
    run = banked(fresh_run(loaded, tmp_path))
    run.validate()
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():  # steps that went the wrong way
        for p in run.params.values():
            p.add_(torch.randn(p.shape, generator=generator))
    assert run.validate()["psnr"] < run.progress.best["psnr"]
    assert run.learning_rate() == pytest.approx(QUICK.lr / QUICK.backoff)
    for name, p in run.params.items():
        assert torch.equal(p, run.best_params[name]), name


def test_the_last_scoring_of_a_budget_does_not_back_off(loaded, tmp_path):
    """No step follows it: a rerun with more minutes goes on from the last step at the same rate."""
    run = banked(fresh_run(loaded, tmp_path))
    run.validate()
    with torch.no_grad():
        for p in run.params.values():
            p.add_(torch.randn(p.shape, generator=torch.Generator().manual_seed(0)))
    run.step()
    last = snapshot(run.params)
    assert run.validate(go_back=False)["psnr"] < run.progress.best["psnr"]
    assert run.learning_rate() == QUICK.lr and run.progress.best_step == 0
    assert all(torch.equal(p, last[k]) for k, p in run.params.items())


def test_a_resumed_run_continues_as_the_uninterrupted_one(loaded, tmp_path):
    whole = banked(fresh_run(loaded, tmp_path / "whole"))
    whole.validate()
    for _ in range(3):
        whole.step()
    whole.save({"test": 1})

    resumed = banked(fresh_run(loaded, tmp_path / "whole"))
    resumed.load(torch.load(tmp_path / "whole" / "state.pt", weights_only=False))
    assert resumed.progress.step == 3 and resumed.progress.initial is not None
    for _ in range(2):
        expected, got = whole.step(), resumed.step()
        assert expected == got
    for name, p in whole.params.items():
        assert torch.equal(p, resumed.params[name]), name


def test_the_kept_step_is_the_best_scored(loaded, tmp_path):
    # A learning rate large enough that some scorings are worse than others.
    run = banked(fresh_run(loaded, tmp_path, replace(QUICK, lr=2e-2)))
    run.validate()
    weights = {0: snapshot(run.params)}
    for _ in range(5):
        for _ in range(3):
            run.step()
        run.validate()
        weights[run.progress.step] = snapshot(run.params)
    history = {h["step"]: h["psnr"] for h in run.progress.history}
    assert len(set(history.values())) > 1
    best = max(history, key=history.get)
    assert run.progress.best_step == best and run.progress.best["psnr"] == history[best]
    assert all(torch.equal(run.best_params[k], weights[best][k]) for k in weights[best])


def test_another_capture_into_the_same_out_is_refused(loaded, base, tmp_path):
    capture, split, model, onnx = loaded
    out = tmp_path / "out"
    fresh_run(loaded, out / ".refine").save({"capture_sha256": "another"})
    with pytest.raises(RefineError, match="refinement of another capture_sha256"):
        refine_module.check_out(out, base[0], {"capture_sha256": capture.sha256})
    (tmp_path / "bundle").mkdir()
    (tmp_path / "bundle" / "manifest.json").write_text("{}")
    with pytest.raises(RefineError, match="holds a bundle that refine did not write"):
        refine_module.check_out(tmp_path / "bundle", base[0], {})
    (tmp_path / "bundle" / "manifest.json").write_text('{"provenance": {"refinement": {}}}')
    with pytest.raises(RefineError, match="holds a finished refinement: pass another --out"):
        refine_module.check_out(tmp_path / "bundle", base[0], {})


def test_interrupted_writes_the_best_step_and_the_same_command_resumes(capture_dir, base, tmp_path, monkeypatch):
    """Ctrl-C at the 8th step writes the bundle of the best validation scoring so far (the bundle's
    writing stubbed: what it is given is checked), keeps the state; the same call resumes to the
    budget's end, writes again and removes the state."""
    written = []

    def record_bundle(base_dir, manifest, model, out, record, staging, band):
        renderer = None if model is None else {k: v.clone() for k, v in model.renderer.state_dict().items()}
        written.append({"renderer": renderer, "record": record, "band": band})
        return type("Written", (), {"model_id": f"refined-{len(written)}"})()

    monkeypatch.setattr(refine_module, "write_bundle", record_bundle)
    out, steps = tmp_path / "refined", {"n": 0}
    original_step = Refinement.step

    def step_then_interrupt(self):
        steps["n"] += 1
        if steps["n"] == 8:
            raise KeyboardInterrupt
        return original_step(self)

    monkeypatch.setattr(Refinement, "step", step_then_interrupt)
    args = dict(base=base[0], checkpoint=base[1], holdout=3, threads=1, device="cpu")
    first = refine(capture_dir, out, COUNTED, **args)
    state = torch.load(out / ".refine" / "state.pt", weights_only=False)
    record = first.record
    assert first.interrupted and record["interrupted"] and record["steps_run"] == 7
    assert record["validation"] == ["v5"] and record["held_out"] == ["v0", "v3", "v6"]
    assert not set(record["training"]) & {"v0", "v3", "v5", "v6"}
    scorings = dict(record["scorings"])
    assert set(scorings) == {0, 4} and record["steps"] == max(scorings, key=scorings.get)
    assert record["validation_psnr"]["after"] == pytest.approx(max(scorings.values()), abs=1e-4)
    assert written[0]["band"] == record["band"] == state["progress"]["best"]["band"]
    if record["steps"] > 0:  # the kept step's weights, not the last step's
        assert all(torch.equal(written[0]["renderer"][k], v) for k, v in state["best_params"].items())
    else:
        assert written[0]["renderer"] is None

    monkeypatch.setattr(Refinement, "step", original_step)
    second = refine(capture_dir, out, COUNTED, **args)
    record = second.record
    assert not second.interrupted and record["steps_run"] == 16 and not (out / ".refine").exists()
    assert set(dict(record["scorings"])) == {0, 4, 8, 12, 16}
    assert record["held_out_psnr"]["before"] == first.record["held_out_psnr"]["before"]  # scored once
    assert record["minutes"] >= first.record["minutes"]


# ------------------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_interrupted_then_resumed_into_an_ordinary_bundle(capture_dir, base, tmp_path, monkeypatch):
    out = tmp_path / "refined"
    steps = {"n": 0}
    original_step = Refinement.step

    def step_then_interrupt(self):
        steps["n"] += 1
        if steps["n"] == 8:
            raise KeyboardInterrupt
        return original_step(self)

    monkeypatch.setattr(Refinement, "step", step_then_interrupt)
    args = dict(base=base[0], checkpoint=base[1], holdout=3, threads=1, device="cpu")
    first = refine(capture_dir, out, COUNTED, **args)
    assert first.interrupted and first.record["steps_run"] == 7 and (out / ".refine" / "state.pt").is_file()
    assert Manifest.load(out).provenance.refinement["interrupted"]  # the best so far, servable
    monkeypatch.setattr(Refinement, "step", original_step)

    second = refine(capture_dir, out, COUNTED, **args)
    record = second.record
    assert not second.interrupted and record["steps_run"] == 16
    assert record["minutes"] >= first.record["minutes"]
    assert not (out / ".refine").exists()  # removed once the budget is spent
    with pytest.raises(RefineError, match="holds a finished refinement"):
        refine(capture_dir, out, COUNTED, **args)
    manifest = Manifest.load(out)
    assert manifest.model_id == second.model_id == manifest.expected_model_id()
    refinement = manifest.provenance.refinement
    assert refinement["base_model_id"] == Manifest.load(base[0]).model_id
    assert refinement["capture"]["folder"] == capture_dir.name and len(refinement["capture"]["sha256"]) == 64
    assert refinement["held_out"] == ["v0", "v3", "v6"] and refinement["validation"] == ["v5"]
    assert refinement["training"] == ["v1", "v2", "v4", "v7", "v8"]
    # The validation scorings: the base's first, the kept step's the best of them (every 4th step;
    # the interruption at step 8 is not scored), and the kept step one of those.
    scored = dict(refinement["scorings"])
    assert set(scored) == {0, 4, 8, 12, 16}
    checks = refinement["validation_psnr"]
    assert checks["before"] == pytest.approx(scored[0], abs=1e-4)
    assert refinement["steps"] == max(scored, key=scored.get)
    assert checks["after"] == pytest.approx(scored[refinement["steps"]], abs=1e-4)
    held = refinement["held_out_psnr"]
    assert set(held["views"]) == {"v0", "v3", "v6"} and math.isfinite(held["after"])
    if refinement["steps"] > 0:
        assert manifest.model_id != Manifest.load(base[0]).model_id
    # The bundle runs as the server runs it (ONNX Runtime, guided sampling included).
    bundle = OnnxBundle(out, threads=1)
    scene = read_capture(capture_dir).scene
    sources = [scene.views[n] for n in ("v1", "v2", "v4")]
    encoded = bundle.encode_scene(
        np.stack([v.image for v in sources]), [v.camera for v in sources], 2.0, 6.0, (0, 0, 0)
    )
    for sampling in ("full", "guided"):
        rgb = bundle.render_target(encoded, scene.views["v0"].camera, scene.near, scene.far, sampling=sampling).rgb
        assert rgb.shape == (HEIGHT, WIDTH, 3) and np.isfinite(rgb).all()
    shutil.rmtree(out)
