"""The pretend lab's truth channel: the physical world (true servo ticks, true lamp output)
from the process that hosts the emulators (simulator.pretend_lab) to the simulated camera in the
acquiring process (simulator.world), over a Unix socket beside the lab's device links, one JSON
line per request: `{"get": "state"}` → `{"ticks": {ID: ticks}, "light_level": x}`."""

from __future__ import annotations

import json
import socket
import socketserver
import threading
from pathlib import Path
from typing import Any

from plumbing.config import ConfigError

__all__ = ["TRUTH_SOCKET", "TruthClient", "TruthHandler"]

TRUTH_SOCKET = "truth.sock"


class TruthClient:
    """The simulated camera's line to a pretend lab's physical truth (see module doc)."""

    def __init__(self, path: Path, timeout_s: float = 5.0) -> None:
        self.path = Path(path)
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._buf = b""
        self._lock = threading.Lock()

    @classmethod
    def beside(cls, device_url: str) -> TruthClient:
        """The truth socket of the pretend lab serving `device_url` (in the same folder)."""
        path = Path(device_url).expanduser().parent / TRUTH_SOCKET
        if not path.exists():
            raise ConfigError(
                f'camera.backend "sim" with serial devices needs a pretend lab serving them: '
                f"no {path} (start `python -m simulator.pretend_lab --dir {path.parent}`)"
            )
        return cls(path)

    def _connect(self) -> socket.socket:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout_s)
        s.connect(str(self.path))
        return s

    def state(self) -> dict[str, Any]:
        with self._lock:
            for attempt in range(2):  # one reconnect: the lab may have been restarted
                try:
                    if self._sock is None:
                        self._sock = self._connect()
                    self._sock.sendall(b'{"get": "state"}\n')
                    while b"\n" not in self._buf:
                        chunk = self._sock.recv(65536)
                        if not chunk:
                            raise ConnectionError("pretend lab closed the truth socket")
                        self._buf += chunk
                    line, self._buf = self._buf.split(b"\n", 1)
                    doc = json.loads(line)
                    doc["ticks"] = {int(k): int(v) for k, v in doc["ticks"].items()}
                    return doc
                except (OSError, ValueError, KeyError):
                    if self._sock is not None:
                        self._sock.close()
                    self._sock, self._buf = None, b""
                    if attempt:
                        raise
        raise AssertionError("unreachable")


class TruthHandler(socketserver.StreamRequestHandler):
    """Serves `server.state()` (a callable) to each `{"get": "state"}` line."""

    def handle(self) -> None:
        state = self.server.state  # type: ignore[attr-defined]
        for line in self.rfile:
            try:
                req = json.loads(line)
                if req.get("get") != "state":
                    raise ValueError("unknown request")
                reply = state()
            except ValueError as exc:
                reply = {"error": str(exc)}
            self.wfile.write((json.dumps(reply) + "\n").encode())
