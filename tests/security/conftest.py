"""Helpers for the attack regression tests: run mapd in a child process and measure it."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

MAPD = [sys.executable, "-m", "mapd"]


def run_mapd(*args: str, timeout: float = 120, **kw: Any) -> subprocess.CompletedProcess[str]:
    """``mapd ARGS`` as a user runs it (a hang fails the test by TimeoutExpired); ``kw`` goes to
    :func:`subprocess.run` (``preexec_fn`` to set a limit, say)."""
    return subprocess.run([*MAPD, *args], capture_output=True, text=True, timeout=timeout, **kw)


def assert_one_error_line(out: subprocess.CompletedProcess[str], *, code: int | None = None) -> str:
    """The command failed with exactly one ``mapd: error:`` line and no traceback; returns the line."""
    assert out.returncode != 0, out.stdout
    if code is not None:
        assert out.returncode == code, out.stderr
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mapd: error: "), out.stderr[-2000:]
    return lines[0]


def measure(code: str, timeout: float = 300) -> dict[str, Any]:
    """Run ``code`` in a fresh interpreter; returns what it printed as JSON on its last line.

    ``code`` sees ``peak_mb()`` (this process's peak resident memory so far, MiB) and ``report(**kw)``
    (print the result). Peak memory is measured in a child so that the test process's own history
    does not hide it.
    """
    prelude = textwrap.dedent(
        """
        import json, resource, sys, time

        def peak_mb():
            # VmHWM: this process's own high-water mark since exec. ru_maxrss keeps the one of the
            # process it was forked from (a pytest worker of hundreds of MiB), which would hide
            # every peak below it.
            try:
                with open("/proc/self/status") as f:
                    for line in f:
                        if line.startswith("VmHWM:"):
                            return int(line.split()[1]) / 1024.0
            except OSError:
                pass
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

        def report(**kw):
            print(json.dumps(kw))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


# In --import-mode=importlib a test module cannot import this file, so the helpers are fixtures.


@pytest.fixture(scope="session")
def mapd_run() -> Callable[..., subprocess.CompletedProcess[str]]:
    return run_mapd


@pytest.fixture(scope="session")
def one_error_line() -> Callable[..., str]:
    return assert_one_error_line


@pytest.fixture(scope="session")
def in_child() -> Callable[..., dict[str, Any]]:
    return measure
