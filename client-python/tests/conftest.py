"""A real scnerf-server for the client's tests: the binary of this checkout (``SCNERF_SERVER_BIN``
to name another) with the parity fixtures' small random-weight bundle, on a free loopback port."""

from __future__ import annotations

import os
import re
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BUNDLE = REPO / "tests/fixtures/parity/bundle"


def server_binary() -> Path:
    explicit = os.environ.get("SCNERF_SERVER_BIN")
    candidates = (
        [Path(explicit)] if explicit else [REPO / "target/debug/scnerf-server", REPO / "target/release/scnerf-server"]
    )
    for path in candidates:
        if path.is_file():
            return path
    pytest.fail(f"no scnerf-server binary at {candidates}: cargo build -p scnerf-server")


class Server:
    def __init__(self, *args: str):
        env = {**os.environ, "RUST_LOG": "warn"}
        cmd = [str(server_binary()), "--bundle", str(BUNDLE), "--addr", "127.0.0.1:0", "--skip-warmup", *args]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        line = self.proc.stdout.readline()
        found = re.search(r"listening on (http://\S+)", line)
        if not found:
            self.proc.kill()
            pytest.fail(f"the server did not start: {line!r} {self.proc.stderr.read()[-2000:]}")
        self.url = found.group(1)
        for _ in range(600):
            try:
                with urllib.request.urlopen(self.url + "/readyz", timeout=5) as r:
                    if r.status == 200:
                        return
            except OSError:
                time.sleep(0.1)
        pytest.fail("the server did not get ready")

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=30)


@pytest.fixture(scope="session")
def server():
    """A server whose source limit is 64x48 pixels (so that image sets are chosen by it)."""
    s = Server("--max-source-pixels", "3072")
    yield s
    s.stop()


@pytest.fixture(scope="session")
def token_server():
    s = Server("--auth-token", "secret-token")
    yield s
    s.stop()


@pytest.fixture(scope="session")
def models_dir(tmp_path_factory) -> Path:
    """The ``--models`` folder of ``models_server``: empty at its start."""
    return tmp_path_factory.mktemp("models")


@pytest.fixture(scope="session")
def models_server(models_dir):
    """A server of the fixture bundle (model ``bundle``, the default) that also serves the bundle
    folders put in ``models_dir`` once reloaded."""
    s = Server("--models", str(models_dir))
    yield s
    s.stop()
