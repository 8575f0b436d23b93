"""The `scnerf-export` command line: what a user reads on stderr."""

import warnings

from scnerf_export import cli


def test_a_warning_is_one_line_of_the_command_like_an_error(monkeypatch, capsys):
    def warns(args):
        warnings.warn("/data/transforms.json: lens distortion coefficients are ignored", UserWarning, stacklevel=2)

    monkeypatch.setattr(cli, "cmd_fixtures", warns)
    assert cli.main(["fixtures", "--out", "unused"]) == 0
    err = capsys.readouterr().err
    assert err == "scnerf-export fixtures: warning: /data/transforms.json: lens distortion coefficients are ignored\n"


def test_the_warning_display_is_restored_after_the_command(monkeypatch):
    shown = warnings.showwarning
    monkeypatch.setattr(cli, "cmd_fixtures", lambda args: None)
    cli.main(["fixtures", "--out", "unused"])
    assert warnings.showwarning is shown
