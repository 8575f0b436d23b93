"""Checkpoint import: the public MVSNeRF file maps completely; bad files fail in one line."""

import zipfile

import pytest
import torch

from scnerf_export.cli import main
from scnerf_export.config import small_config
from scnerf_export.model.checkpoint import CheckpointError, load_checkpoint, load_mvsnerf, save_checkpoint
from scnerf_export.rigs import random_model


def test_public_checkpoint_maps_every_tensor(public_checkpoint):
    model, provenance = load_mvsnerf(public_checkpoint)
    raw = torch.load(public_checkpoint, map_location="cpu", weights_only=True)
    n_raw = sum(len(raw[k]) for k in ("network_mvs_state_dict", "network_fn_state_dict"))
    assert len(model.state_dict()) == n_raw
    params = sum(p.numel() for p in model.parameters())
    assert params == 341_858 + 126_788 - sum(  # the checkpoint's counts include BN running statistics
        t.numel() for k, t in raw["network_mvs_state_dict"].items() if "running" in k or "num_batches" in k
    )
    assert provenance["source_sha256"] == "84c2a397760d5e717c21faee9c4f8f8f8a1ba22b378b10971c44f4a0b932c124"
    assert torch.equal(model.renderer.m1.feature_gate.weight, raw["network_fn_state_dict"]["nerf.pts_bias.weight"])


def test_project_checkpoint_round_trips(tmp_path):
    model = random_model(small_config("scnerf"), seed=0)
    save_checkpoint(tmp_path / "c.pt", model, {"training": {"steps": 3}})
    loaded, provenance = load_checkpoint(tmp_path / "c.pt")
    assert loaded.cfg == model.cfg
    assert provenance["training"] == {"steps": 3}
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])


def _bad_files(tmp_path, public_checkpoint=None):
    (tmp_path / "text.tar").write_text("not a checkpoint\n")
    with zipfile.ZipFile(tmp_path / "foreign.zip", "w") as z:
        z.writestr("hello.txt", "hi")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    model = random_model(small_config("scnerf"), seed=0)
    save_checkpoint(tmp_path / "ours.pt", model, {})
    state = torch.load(tmp_path / "ours.pt", weights_only=True)
    state["state_dict"]["renderer.m1.feature_gate.weight"] = torch.zeros(3, 3)
    torch.save(state, tmp_path / "wrong_shape.pt")
    state["state_dict"].pop("renderer.m1.feature_gate.weight")
    torch.save(state, tmp_path / "missing.pt")
    return ["missing_file.pt", "text.tar", "foreign.zip", "other.pt", "wrong_shape.pt", "missing.pt"]


def test_bad_checkpoints_raise_one_line_errors(tmp_path):
    for name in _bad_files(tmp_path):
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(tmp_path / name)
        assert "\n" not in str(info.value) and name in str(info.value)


def test_truncated_public_checkpoint(tmp_path, public_checkpoint):
    data = public_checkpoint.read_bytes()
    (tmp_path / "cut.tar").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError):
        load_mvsnerf(tmp_path / "cut.tar")


def test_mvsnerf_tensors_on_a_foreign_layout_are_refused(tmp_path):
    torch.save(
        {
            "network_mvs_state_dict": {"feature.conv0.0.conv.weight": torch.zeros(8, 3, 3, 3)},
            "network_fn_state_dict": {"nerf.extra.weight": torch.zeros(1)},
        },
        tmp_path / "odd.tar",
    )
    with pytest.raises(CheckpointError, match="left over"):
        load_mvsnerf(tmp_path / "odd.tar")


def test_cli_exits_non_zero_with_one_line(tmp_path, capsys):
    _bad_files(tmp_path)
    for name in ("text.tar", "wrong_shape.pt"):
        assert main(["export", "--checkpoint", str(tmp_path / name), "--out", str(tmp_path / "b")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "error" in err
    assert not (tmp_path / "b").exists()
