"""`scnerf-export refine DATA --out DIR`: a bundle's network fine-tuned on one capture's own views,
written as an ordinary bundle.

Per-scene refinement, as MVSNeRF's paper fine-tunes on a scene's images, within what a bundle can
serve: the server builds a volume from whatever three views a request brings, so what refine
changes is the network, not a volume. The encoder and volume net (G1, G2) stay the base bundle's
graphs; the renderer's trunk M1 and its heads (M2, the geometry and appearance rectifiers, M4)
train on banked rays (``refine_bank``): each training view rendered as the server renders it,
from the 3 training views nearest to it (``cameras.rank_sources``), at the S uniform samples of
the capture's [near, far]. Which of those train is the recipe's ``train`` (docs/results.md,
"Refining a capture", says what the recipe's choices gave).

Validation views (by default 1 in 8 of the views left after the hold-out, ``split_views``) and
held-out views are never sources and never drawn for a step. A fixed sample of the validation
views' pixels is scored as the server renders them (the band stage by each of its rules) before
training, every ``score_every_s`` seconds of training and at the end: the scored step with the best
mean PSNR, with its band rule, is what the bundle keeps (the base itself if no step beats it), and
a scoring below the best sends training back to the best weights at a smaller learning rate
(``back_off``). The held-out views are scored twice, for the record only: the base before
training, the kept step by its band rule when the bundle is written.

The run keeps to a time budget (``minutes``: banking, training, scoring and writing the bundle),
and to a budget of ``steps`` where the recipe sets one.
Views are banked in an order that spreads over the capture (``spread_order``), between stretches
of training as long as the banking took, so a short budget trains on views from all around. The
work folder (``OUT/.refine``) holds the state (weights, optimiser, best step, time spent) and the
banks: Ctrl-C (or SIGTERM) stops, writes the bundle of the best step so far and keeps the state,
and the same command run again resumes until the budget is spent. A run that spends its budget
removes the work folder (``keep_state`` keeps it: a rerun with more minutes then goes on).

Steps run on ``device`` (CUDA where PyTorch sees a GPU, by default): the renderer and each step's
rays there, the banks in host memory. The encoder and volume graphs run in ONNX Runtime on the CPU,
once per banked view.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import shutil
import signal
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from .. import __version__
from ..export.manifest import BAND_RULES
from ..runtime.band import Sources
from ..runtime.onnx_pipeline import OnnxBundle
from .from_scratch import hardware
from .refine_bank import Encoded, PointBank, bank_view, score, shade, sweep_in_torch
from .refine_bundle import base_model, write_bundle
from .refine_capture import MAX_SOURCE_PIXELS, Capture, Split, read_capture, split_views, spread_order

# What may train, by the renderer's modules (the encoder and volume graphs never do).
MODULES = {"trunk": ("m1",), "heads": ("m2", "geometry", "appearance", "colour_head")}


def default_bundle() -> Path:
    """$SCNERF_BUNDLE (the server's variable; the container sets it), else the repository's default bundle."""
    return Path(os.environ.get("SCNERF_BUNDLE") or Path(__file__).resolve().parents[3] / "bundles" / "default")


@dataclass(frozen=True)
class Recipe:
    minutes: float = 15.0
    train: tuple[str, ...] = ("trunk", "heads")
    lr: float = 1e-3
    rays: int = 256  # per step
    rays_per_view: int = 4096  # banked per training view, at most
    bank_rays: int = 1 << 17  # banked over all training views, at most (~16 KB each)
    scored_rays: int = 8192  # scored over all validation views, and as many over all held-out views
    min_scored_rays: int = 512  # scored per validation or held-out view, at least
    score_every_s: float = 90.0  # seconds of training between scorings
    # A budget of steps besides the minutes, and scorings every so many steps instead of seconds:
    # a run that does the same work on any machine (tests, comparisons of recipes).
    steps: int | None = None
    score_every_steps: int | None = None
    backoff: float = 3.0  # a scoring below the best: the best weights back, the learning rate divided by this
    write_reserve_s: float = 60.0  # kept for writing the bundle at the end of the budget
    seed: int = 0

    def __post_init__(self) -> None:
        unknown = sorted(set(self.train) - set(MODULES))
        if unknown or not self.train:
            raise ValueError(f"train: {', '.join(unknown) or 'nothing'}; choose from {', '.join(MODULES)}")
        if not self.minutes > 0:
            raise ValueError(f"minutes must be positive, got {self.minutes}")
        if not self.backoff >= 1:
            raise ValueError(f"backoff must be at least 1, got {self.backoff}")
        for name in ("steps", "score_every_steps"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")


class RefineError(ValueError):
    """An --out folder refine cannot use; the message is one line, fit for a CLI."""


# ---------------------------------------------------------------------------------------- parameters


def trainable(renderer, train: tuple[str, ...]) -> dict[str, torch.nn.Parameter]:
    """The renderer's parameters of the modules ``train`` names (by their state-dict names), with
    gradients; every other parameter frozen."""
    for p in renderer.parameters():
        p.requires_grad_(False)
    chosen = {}
    for group in train:
        for module in MODULES[group]:
            if getattr(renderer, module, None) is None:  # mvsnerf has no rectifiers
                continue
            for name, p in getattr(renderer, module).named_parameters():
                chosen[f"{module}.{name}"] = p.requires_grad_(True)
    return chosen


def snapshot(params: dict[str, torch.nn.Parameter]) -> dict[str, torch.Tensor]:
    return {k: p.detach().clone() for k, p in params.items()}


def restore(params: dict[str, torch.nn.Parameter], values: dict[str, torch.Tensor]) -> None:
    with torch.no_grad():
        for k, p in params.items():
            p.copy_(values[k])


# ----------------------------------------------------------------------------------------- the run


@dataclass
class Progress:
    """What a run has done; saved with the weights, so that a rerun resumes."""

    step: int = 0
    seconds: float = 0.0  # banking, training and scoring, over every run
    best_step: int = 0
    initial: dict | None = None  # the base's validation scores
    best: dict | None = None  # the kept step's
    held_out_before: dict | None = None  # the base's held-out scores, for the record only
    history: list = field(default_factory=list)  # every validation scoring: step, seconds, scores


@dataclass
class ScoredViews:
    """Views scored as the server renders them (validation or held-out): a fixed sample of their
    pixels, banked, and each view's three sources for the band stage."""

    names: list[str]
    bank: PointBank
    sources: list[Sources]

    def scores(self, renderer, rules: tuple[str, ...] = BAND_RULES) -> dict[str, dict]:
        """By each band rule of ``rules``: ``refine_bank.score``."""
        return score(renderer, self.bank, self.names, self.sources, rules)


class Refinement:
    """One capture's refinement: the banks, the optimiser, the schedule and the best step so far."""

    def __init__(
        self, model, capture: Capture, split: Split, onnx: OnnxBundle, recipe: Recipe, work: Path, device="cpu"
    ):
        self.model = model.to(device).eval()
        self.renderer = model.renderer
        self.capture, self.split, self.onnx, self.recipe, self.work = capture, split, onnx, recipe, work
        self.params = trainable(self.renderer, recipe.train)
        self.optimiser = torch.optim.Adam(self.params.values(), lr=recipe.lr)
        self.generator = torch.Generator().manual_seed(recipe.seed)
        self.progress = Progress()
        self.best_params = snapshot(self.params)
        self.pending = spread_order(capture.scene, split.training)
        self.banked: list[str] = []
        self.train_bank: PointBank | None = None
        self.validation: ScoredViews | None = None
        self.held_out: ScoredViews | None = None
        self.clock = time.perf_counter()
        self.since_bank = self.since_score = self.bank_seconds = self.score_seconds = self.held_seconds = 0.0
        self.loss = float("nan")
        self.identity: dict = {}

    # ------------------------------------------------------------------ time

    def elapsed(self) -> float:
        return time.perf_counter() - self.clock

    def start_clock(self) -> None:
        self.clock = time.perf_counter() - self.progress.seconds

    # ------------------------------------------------------------------ banks

    def _pixels(self, name: str, count: int) -> np.ndarray:
        camera = self.capture.scene.views[name].camera
        seed = int.from_bytes(hashlib.sha256(f"{self.recipe.seed}/{name}".encode()).digest()[:4], "little")
        total = camera.width * camera.height
        return np.sort(np.random.default_rng(seed).choice(total, size=min(count, total), replace=False))

    def _bank(self, name: str, index: int, count: int) -> PointBank:
        """The banked rays of view ``name``: read from the work folder, or built and written there."""
        pick = self._pixels(name, count)
        key = hashlib.sha256(name.encode()).hexdigest()[:16]
        path = self.work / "banks" / f"{key}-{len(pick)}-v{PointBank.FORMAT}.pt"
        if path.is_file():
            bank = PointBank(**torch.load(path, weights_only=True))
            bank.view.fill_(index)
            return bank
        scene = self.capture.scene
        sources = [scene.views[s] for s in self.split.sources[name]]
        encoded = self.onnx.encode_scene(
            np.stack([v.image for v in sources]), [v.camera for v in sources], scene.near, scene.far, scene.background
        )
        bank = bank_view(
            self.renderer, Encoded.of(encoded), scene.views[name], pick, scene.near, scene.far, scene.background, index
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(bank.__dict__, path.with_suffix(".tmp"))
        path.with_suffix(".tmp").replace(path)
        return bank

    def _bank_scored(self, names: list[str]) -> ScoredViews:
        count = max(self.recipe.min_scored_rays, self.recipe.scored_rays // len(names))
        bank = PointBank.concat([self._bank(name, i, count) for i, name in enumerate(names)])
        views, sources = self.capture.scene.views, []
        for name in names:
            triple = [views[s] for s in self.split.sources[name]]
            sources.append(Sources.of_views(np.stack([v.image for v in triple]), [v.camera for v in triple]))
        return ScoredViews(names, bank, sources)

    def bank_scored_views(self) -> None:
        """Banks the validation and the held-out views' scored pixels (never the rays steps draw from)."""
        self.validation = self._bank_scored(self.split.validation)
        self.held_out = self._bank_scored(self.split.held_out)

    def bank_next(self) -> None:
        """Banks the next training view and adds it to the rays steps draw from."""
        start = self.elapsed()
        name = self.pending.pop(0)
        count = min(self.recipe.rays_per_view, self.recipe.bank_rays // len(self.split.training))
        bank = self._bank(name, len(self.banked), count)
        self.banked.append(name)
        self.train_bank = bank if self.train_bank is None else PointBank.concat([self.train_bank, bank])
        self.bank_seconds, self.since_bank = self.elapsed() - start, 0.0

    def wants_score(self) -> bool:
        """A scoring is due: every ``score_every_steps`` steps where the recipe counts steps, else
        after ``score_every_s`` seconds of training."""
        every = self.recipe.score_every_steps
        if every is not None:
            return self.progress.step % every == 0
        return self.since_score >= self.recipe.score_every_s

    def steps_spent(self) -> bool:
        return self.recipe.steps is not None and self.progress.step >= self.recipe.steps

    def wants_bank(self) -> bool:
        """Bank the next view when none is banked, or after training as long as the last banking took."""
        return bool(self.pending) and (self.train_bank is None or self.since_bank >= self.bank_seconds)

    # ------------------------------------------------------------------ steps and scores

    def step(self) -> float:
        """One optimiser step on random banked rays of the training views; the loss before it."""
        start = self.elapsed()
        idx = torch.randint(len(self.train_bank), (self.recipe.rays,), generator=self.generator)
        truth = self.train_bank.truth[idx].to(self.device)
        loss = torch.mean((shade(self.renderer, self.train_bank, idx) - truth) ** 2)
        self.optimiser.zero_grad(set_to_none=True)
        loss.backward()
        self.optimiser.step()
        self.progress.step += 1
        spent = self.elapsed() - start
        self.since_bank += spent
        self.since_score += spent
        self.loss = float(loss.detach())
        return self.loss

    @property
    def device(self) -> torch.device:
        return next(self.renderer.parameters()).device

    def validate(self, go_back: bool = True) -> dict:
        """Scores the validation views as the server renders them: the base by its bundle's band
        rule, a step by the rule that scores it best. Keeps the weights when they beat every scored
        step before; when they do not and ``go_back``, goes back to the best ones (``back_off``)."""
        start = self.elapsed()
        by_rule = self.validation.scores(self.renderer)
        self.score_seconds = self.elapsed() - start
        p = self.progress
        rule = self.onnx.manifest.band if p.initial is None else max(by_rule, key=lambda r: by_rule[r]["psnr"])
        result = {**by_rule[rule], "band": rule, "psnr_by_band": {r: s["psnr"] for r, s in by_rule.items()}}
        p.history.append({"step": p.step, "seconds": self.elapsed(), "lr": self.learning_rate(), **result})
        if p.initial is None:
            p.initial = p.best = result
        elif result["psnr"] > p.best["psnr"]:
            p.best, p.best_step, self.best_params = result, p.step, snapshot(self.params)
        elif go_back:
            self.back_off()
        self.since_score = 0.0
        return result

    def score_held_out(self, rule: str) -> dict:
        """The held-out views' scores by the band rule ``rule``: for the record, never for a choice."""
        start = self.elapsed()
        result = {**self.held_out.scores(self.renderer, (rule,))[rule], "band": rule}
        self.held_seconds = self.elapsed() - start
        return result

    def score_base(self) -> tuple[dict, dict]:
        """The base's validation and held-out scores, by its bundle's band rule, once per run."""
        self.progress.held_out_before = self.score_held_out(self.onnx.manifest.band)
        return self.validate(), self.progress.held_out_before

    def held_out_after(self) -> dict:
        """The kept step's held-out scores, by its band rule: the kept weights are restored."""
        p = self.progress
        if p.best_step == 0:
            return p.held_out_before
        restore(self.params, self.best_params)
        return self.score_held_out(p.best["band"])

    def learning_rate(self) -> float:
        return self.optimiser.param_groups[0]["lr"]

    def back_off(self) -> None:
        """The best step's weights again, a smaller learning rate and fresh moments: the steps since
        the best went the wrong way for the validation views. A capture the base already fits (DTU's,
        which MVSNeRF trained on) needs a far smaller rate than one it does not (LLFF's)."""
        restore(self.params, self.best_params)
        lr = self.learning_rate() / self.recipe.backoff
        self.optimiser = torch.optim.Adam(self.params.values(), lr=lr)

    # ------------------------------------------------------------------ state

    def save(self, identity: dict | None = None) -> None:
        """Writes the state a rerun resumes from (``identity``: what it must share with this run)."""
        if identity is not None:
            self.identity = identity
        self.progress.seconds = self.elapsed()
        state = {
            "identity": self.identity,
            "progress": asdict(self.progress),
            "params": snapshot(self.params),
            "best_params": self.best_params,
            "optimiser": self.optimiser.state_dict(),
            "generator": self.generator.get_state(),
        }
        path = self.work / "state.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(state, path.with_suffix(".tmp"))
        path.with_suffix(".tmp").replace(path)

    def load(self, state: dict) -> None:
        self.progress = Progress(**state["progress"])
        restore(self.params, state["params"])
        self.best_params = {k: v.to(self.device) for k, v in state["best_params"].items()}
        self.optimiser.load_state_dict(state["optimiser"])
        self.generator.set_state(state["generator"])


# ------------------------------------------------------------------------------------------ schedule


def status(run: Refinement) -> str:
    p = run.progress
    scored = "" if p.best is None else f", validation {p.history[-1]['psnr']:.2f} dB (best {p.best['psnr']:.2f})"
    views = f"views {len(run.banked)}/{len(run.split.training)}"
    return f"step {p.step}, loss {run.loss:.4f}{scored}, {views}"


def gain_line(what: str, before: dict, after: dict) -> str:
    """``what``'s PSNR ``after`` and its gain over ``before``, and on object masks where there are some."""
    line = f"{what} PSNR {after['psnr']:.2f} dB ({after['psnr'] - before['psnr']:+.2f})"
    if "psnr_masked" in after:
        line += f", masked {after['psnr_masked']:.2f} dB ({after['psnr_masked'] - before['psnr_masked']:+.2f})"
    return line


def report(run: Refinement, result: dict) -> str:
    p = run.progress
    line = f"step {p.step} ({run.elapsed() / 60:.1f} min): " + gain_line("validation", p.initial, result)
    return line + f", band filled {result['band'].replace('_', ' ')}; best step {p.best_step}"


def train_to(run: Refinement, deadline: float, bar: tqdm, log) -> None:
    """Banks views and trains until ``deadline`` (seconds of the run's clock) or the recipe's steps,
    validating as it goes."""
    while run.elapsed() < deadline and not run.steps_spent():
        if run.wants_bank():
            bar.set_description(f"refine (banking {run.pending[0]})")
            run.bank_next()
            bar.set_description("refine")
        elif run.train_bank is None:
            break  # every view banked and none to train on: cannot happen after split_views
        else:
            loss = run.step()
            log.write(json.dumps({"step": run.progress.step, "loss": loss, "seconds": run.elapsed()}) + "\n")
            if run.wants_score():
                tqdm.write(report(run, run.validate()))
                run.save()  # a run killed outright resumes from here
        bar.n = min(int(run.elapsed()), bar.total)
        bar.set_postfix_str(status(run), refresh=False)
        bar.refresh()


def finish(run: Refinement, bar: tqdm) -> None:
    """The last validation, if a step came after the one before. No step follows it, so it does not
    back off: a rerun with more minutes (``keep_state``) goes on as a longer run would have."""
    if run.progress.history and run.progress.history[-1]["step"] != run.progress.step:
        tqdm.write(report(run, run.validate(go_back=False)))
    bar.n = min(int(run.elapsed()), bar.total)
    bar.set_postfix_str(status(run))


@contextmanager
def sigterm_as_interrupt():
    """SIGTERM (a Kubernetes Job deleted, `docker stop`) handled as Ctrl-C: the best so far is written."""

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# ------------------------------------------------------------------------------------------ the command

DEVICES = ("auto", "cuda", "cpu")


def resolve_device(name: str) -> torch.device:
    """``cuda``, ``cpu``, or ``auto``: CUDA where PyTorch sees a GPU, else the CPU."""
    if name not in DEVICES:
        raise RefineError(f"--device {name}: choose {', '.join(DEVICES)}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    elif name == "cuda" and not torch.cuda.is_available():
        raise RefineError("--device cuda: PyTorch sees no CUDA GPU (a CPU-only torch, or no driver); pass --device cpu")
    return torch.device(name)


@dataclass
class Result:
    out: Path
    model_id: str
    record: dict
    interrupted: bool


def identity_of(about: dict, capture: Capture, split: Split, recipe: Recipe) -> dict:
    """What a resumed run must share with the run it resumes."""
    return {
        "base_model_id": about["base_model_id"],
        "capture_sha256": capture.sha256,
        "held_out": split.held_out,
        "validation": split.validation,
        "training": split.training,
        "train": list(recipe.train),
    }


def check_out(out: Path, base: Path, identity: dict) -> dict | None:
    """The saved state of an earlier run into ``out`` (None for a fresh one); an error for a folder
    refine may not write or a run of another capture, base or split."""
    if out.resolve() == base.resolve():
        raise RefineError("--out is the base bundle: refine writes a new bundle")
    path = out / ".refine" / "state.pt"
    if not path.is_file():
        if (out / "manifest.json").is_file():
            what = "a finished refinement" if refined_bundle(out) else "a bundle that refine did not write"
            raise RefineError(f"{out} holds {what}: pass another --out, or remove {out}")
        return None
    state = torch.load(path, weights_only=False, map_location="cpu")
    differ = [k for k in identity if state["identity"].get(k) != identity[k]]
    if differ:
        raise RefineError(
            f"{out} holds the refinement of another {', '.join(differ)}: pass another --out, or remove {out}"
        )
    return state


def refined_bundle(folder: Path) -> bool:
    """Whether ``folder``'s manifest says refine wrote it."""
    try:
        return "refinement" in json.loads((folder / "manifest.json").read_text()).get("provenance", {})
    except (OSError, ValueError, AttributeError):
        return False


def before_after(before: dict, after: dict, names: list[str], pixels: int) -> dict:
    """PSNR ``before`` and ``after`` (means, masked means, per view) of the views ``names``."""
    record = {"before": before["psnr"], "after": after["psnr"]}
    if "psnr_masked" in before:
        record.update(masked_before=before["psnr_masked"], masked_after=after["psnr_masked"])
    record["views"] = {n: [before["views"][n], after["views"][n]] for n in names}
    record["pixels"] = pixels
    return record


def refinement_record(run: Refinement, about: dict, held_out_after: dict, interrupted: bool) -> dict:
    """``provenance.refinement`` of the bundle written."""
    p, recipe, split = run.progress, run.recipe, run.split
    return {
        "exporter_version": __version__,
        **about,
        "capture": run.capture.describe(),
        "held_out": split.held_out,
        "validation": split.validation,
        "training": split.training,
        "trained": sorted(m for g in recipe.train for m in MODULES[g] if getattr(run.renderer, m, None) is not None),
        "recipe": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(recipe).items()},
        "sampling": f"{run.renderer.cfg.samples} uniform samples per ray on the capture's [near, far]",
        "band": p.best["band"],
        "steps": p.best_step,
        "steps_run": p.step,
        "minutes": round(run.elapsed() / 60.0, 2),
        "validation_psnr": before_after(p.initial, p.best, split.validation, len(run.validation.bank)),
        "held_out_psnr": before_after(p.held_out_before, held_out_after, split.held_out, len(run.held_out.bank)),
        "scorings": [[h["step"], round(h["psnr"], 4)] for h in p.history],
        "selection": "the validation scoring with the best mean PSNR, the base included, with the band rule that "
        "scores it best; held-out views scored for the record only, the base and the kept step (neither "
        "validation nor held-out views are ever sources or in a step)",
        "hardware": hardware(),
        "device": str(run.device),
        "interrupted": interrupted,
    }


def keep_freed_memory() -> None:
    """Large blocks from the heap, and freed memory kept there for the next block. glibc otherwise
    maps every block above its threshold anew and returns it when freed, and the page faults of
    each step's activations and each bank's volume made a step 1.5x and a bank 2-3x as long on the
    development machine (PyTorch's CPU tuning guide recommends an allocator that keeps memory, for
    the same reason). Process-wide, so the command sets it, not the library; nothing off glibc."""
    m_trim_threshold, m_mmap_max = -1, -4
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(m_mmap_max, 0)
        libc.mallopt(m_trim_threshold, 1 << 30)
    except (OSError, AttributeError):
        pass


def refine(
    data: str | Path,
    out: str | Path,
    recipe: Recipe = Recipe(),
    base: str | Path | None = None,
    checkpoint: str | Path | None = None,
    fmt: str | None = None,
    downscale: int | None = None,
    max_pixels: int = MAX_SOURCE_PIXELS,
    holdout: int | None = None,
    targets: list[str] | None = None,
    validation: list[str] | None = None,
    threads: int | None = None,
    keep_state: bool = False,
    near: float | None = None,
    far: float | None = None,
    ignore_distortion: bool = False,
    device: str = "auto",
) -> Result:
    """Refine ``base`` (default :func:`default_bundle`) on the capture ``data``; write the bundle to
    ``out``. The work folder (``out/.refine``: state and banks) is removed once the budget is spent,
    unless ``keep_state``. ``near``/``far`` override the capture's depth range (its files', else its
    poses'); ``ignore_distortion`` uses distorted photos as pinhole (:func:`.refine_capture.read_capture`);
    ``device``: :func:`resolve_device`."""
    if threads:
        torch.set_num_threads(threads)
    out, base = Path(out), Path(base) if base else default_bundle()
    where = resolve_device(device)
    capture = read_capture(data, fmt, downscale, max_pixels, near, far, ignore_distortion)
    split = split_views(capture.scene, holdout, targets, validation)
    model, manifest, about = base_model(base, checkpoint)
    identity = identity_of(about, capture, split, recipe)
    state = check_out(out, base, identity)
    onnx = OnnxBundle(base, threads=threads, plane_sweep=sweep_in_torch)
    run = Refinement(model, capture, split, onnx, recipe, out / ".refine", where)
    run.identity = identity
    if state is not None:
        run.load(state)
    interrupted = False
    try:
        with sigterm_as_interrupt():
            run_budget(run, about)
    except KeyboardInterrupt:
        interrupted = True
        tqdm.write("interrupted: writing the bundle of the best step so far; run the same command again to resume")
    result = write(run, manifest, base, out, about, identity, interrupted)
    if not (interrupted or keep_state):
        shutil.rmtree(run.work, ignore_errors=True)
    return result


def run_budget(run: Refinement, about: dict) -> None:
    """The validation and held-out views banked and the base scored, then banking and training to
    the end of the budget, less what the last scorings and the bundle's writing take."""
    recipe = run.recipe
    budget = recipe.minutes * 60.0
    run.start_clock()
    if run.elapsed() >= budget - recipe.write_reserve_s:
        return
    bar = tqdm(
        total=int(budget),
        initial=int(run.elapsed()),
        unit="s",
        desc="refine (banking validation and held-out views)",
        bar_format="{desc}{percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}",
        dynamic_ncols=True,
    )
    run.work.mkdir(parents=True, exist_ok=True)
    with open(run.work / "log.jsonl", "a") as log:
        try:
            run.bank_scored_views()
            if run.progress.initial is None:
                validation, held_out = run.score_base()
                tqdm.write(
                    f"base {about['base_model_id']}: validation PSNR {validation['psnr']:.2f} dB, "
                    f"held-out PSNR {held_out['psnr']:.2f} dB (the record's before)"
                )
            bar.set_description("refine")
            last_scorings = run.score_seconds + run.held_seconds
            train_to(run, budget - recipe.write_reserve_s - last_scorings, bar, log)
            finish(run, bar)
        finally:
            bar.close()


def write(run: Refinement, manifest, base: Path, out: Path, about: dict, identity: dict, interrupted: bool) -> Result:
    """Saves the run's state, scores the kept step's held-out views and writes its bundle (the
    base's renderer if no step beat it)."""
    run.save(identity)
    p = run.progress
    if p.initial is None:
        if interrupted:
            raise KeyboardInterrupt
        raise RefineError(f"the budget of {run.recipe.minutes:g} minutes ended before the base was scored")
    if run.held_out is None:  # resumed with its budget spent: nothing banked in this run
        run.bank_scored_views()
    held_out = run.held_out_after()
    tqdm.write(f"kept step {p.best_step}: " + gain_line("held-out", p.held_out_before, held_out))
    record = refinement_record(run, about, held_out, interrupted)
    model = None
    if p.best_step > 0:
        restore(run.params, run.best_params)
        model = run.model.cpu()  # the graphs are exported and checked on the CPU; nothing trains after
    written = write_bundle(base, manifest, model, out, record, run.work / "staging", p.best["band"])
    return Result(out, written.model_id, record, interrupted)
