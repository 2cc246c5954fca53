"""Rank 0 in this process, rank 1 in a child running a script: a real two-rank gloo group on loopback."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest


@contextlib.contextmanager
def peer_rank(monkeypatch: pytest.MonkeyPatch, script: str) -> Iterator[None]:
    """Start rank 1 as ``python -c script PORT`` and set this process's torchrun variables for rank 0
    of the same group; on exit wait for the child and fail with its output if it did not exit 0."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = str(sock.getsockname()[1])
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    child = subprocess.Popen([sys.executable, "-c", script, port], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    for k, v in {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": port,
                 "GLOO_SOCKET_IFNAME": "lo"}.items():
        monkeypatch.setenv(k, v)
    try:
        yield
    finally:
        log, _ = child.communicate(timeout=120)
    assert child.returncode == 0, log
