"""A pretend lab: a rig's emulated servo bus and light controller in a process of their own,
on pseudo-terminals, as a USB serial adapter appears to the host.

    python -m simulator.pretend_lab --rig RIG.toml --scene SCENE.toml --dir DIR

serves
- `DIR/dxl`   → the Dynamixel Protocol 2.0 bus emulator's pty (point `[bus] url` here),
- `DIR/light` → the light-controller emulator's pty (`[light] url`, backend "gonio-ascii"),
- `DIR/scpi`  → the same lamp behind a SCPI power-supply emulator (simulator.scpi; backend
  "scpi", `url = "ASRL<DIR>/scpi::INSTR"` through pyvisa-py; full scale from `[light.scpi]`),
- `DIR/truth.sock` → the physical world for the simulated camera: one JSON line per request,
  `{"get": "state"}` → `{"ticks": {ID: ticks}, "light_level": x}` (the arms' true positions
  and the lamp's true output, what an image would show — never what a driver believes),
- `DIR/ready` once all three are served (its content: this process's pid).

The emulators run on the wall clock (rig files here use `clock = "system"`). The acquiring
process — the unmodified `gonio` command line — opens the ptys through the real
`dynamixel_sdk` and pySerial; killing it (even with SIGKILL) leaves the lab running, as a real
rig stays powered, so a resume finds the servos where they stopped. SIGTERM/SIGINT end the lab
and write `DIR/state.json` (torque per servo, lamp on, transport errors), the emulators' own
state for tests.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socketserver
import sys
import threading
import time
from pathlib import Path
from typing import Any

from acquisition.clock import SystemClock
from acquisition.config import RigConfig, load_rig
from plumbing.config import ConfigError
from simulator.truth_channel import TRUTH_SOCKET, TruthHandler

__all__ = ["PretendLab", "main"]


class _Server(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True
    allow_reuse_address = True


def _relink(link: Path, target: str) -> None:
    tmp = link.with_name(f".{link.name}.{os.getpid()}")
    os.symlink(target, tmp)
    os.replace(tmp, link)  # atomic: a reader never sees the link missing


class PretendLab:
    """The emulators of `rig` + `scene` served on ptys and a truth socket in `folder`."""

    def __init__(self, rig: RigConfig, scene: Any, folder: Path) -> None:
        from simulator.dxl.transport import PtyTransport
        from simulator.scene import world_scene
        from simulator.scpi import ScpiSupply
        from simulator.world import EmulatedDevices

        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        # The scene's camera half is the simulated camera's world; a rig with a real camera
        # (e.g. Aravis and its fake GigE camera) needs only the servos and the lamp from it.
        world = world_scene(scene, rig) if rig.camera.backend == "sim" else scene
        self.devices = EmulatedDevices(rig, world, SystemClock())
        self.rig = rig
        full_scale = rig.light.scpi.full_scale if rig.light.scpi is not None else 1.0
        self.scpi = ScpiSupply(self.devices.light, name=rig.name, full_scale=full_scale)
        self.transports = [
            PtyTransport(self.devices.bus),
            PtyTransport(self.devices.light),
            PtyTransport(self.scpi),
        ]
        for name, t in zip(("dxl", "light", "scpi"), self.transports, strict=True):
            _relink(self.folder / name, t.port_path)
        sock = self.folder / TRUTH_SOCKET
        if sock.exists():
            sock.unlink()
        self.server = _Server(str(sock), TruthHandler)
        self.server.state = self.devices.state  # type: ignore[attr-defined]
        self._thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self._thread.start()
        (self.folder / "ready").write_text(str(os.getpid()))

    def state(self) -> dict[str, Any]:
        bus, light = self.devices.bus, self.devices.light
        return {
            "torque_enable": {
                str(a.id): bus.servo(a.id).register("torque_enable") for a in self.rig.axes
            },
            "light_on": light.is_on,
            "light_fault": light.fault,
            "scpi_errors": list(self.scpi.errors),
            "pty_errors": [repr(t.error) for t in self.transports if t.error is not None],
        }

    def close(self) -> None:
        state = self.state()
        self.server.shutdown()
        self.server.server_close()
        for t in self.transports:
            t.close()
        tmp = self.folder / "state.json.tmp"
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.folder / "state.json")
        (self.folder / "ready").unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    from simulator.scene import load_scene

    ap = argparse.ArgumentParser(prog="python -m simulator.pretend_lab", description=__doc__)
    ap.add_argument("--rig", type=Path, required=True, help="rig file (servo ids, models)")
    ap.add_argument("--scene", type=Path, required=True, help="the emulated world")
    ap.add_argument("--dir", type=Path, required=True, help="where the ptys and socket go")
    ns = ap.parse_args(argv)
    try:
        lab = PretendLab(load_rig(ns.rig), load_scene(ns.scene), ns.dir)
    except ConfigError as exc:
        sys.stderr.write(f"error: {exc}\n")
        return 2
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    print(f"pretend lab serving {ns.dir}/dxl, {ns.dir}/light, {ns.dir}/{TRUTH_SOCKET}", flush=True)
    while not done.wait(0.2):
        time.sleep(0)
    lab.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
