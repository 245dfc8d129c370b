"""``hydrosoft-stack check CONFIG``: probe every device a stack config names and say what answers, without moving
the arm.

Per arm: the UR controller's dashboard (29999) and script (30003) ports and one RTDE data package (no control
script is uploaded, so nothing can move); the FT 300 (the port opens, the stream starts, one wrench arrives, the
stream is stopped again); per stack: the tag camera (one frame, lab mode) and its calibration file (lab mode: it
loads, with intrinsics and ``T_base_camera``); per arm in lab mode, the Soft Bubble's depth camera (one 16-bit
frame of the configured size) and its reference membrane file (it loads, at the camera's size). In sim mode the same probes run against a running ``sim_world``'s simulated devices. Exit
status 0 when every probe answered, 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import time
from dataclasses import asdict, dataclass

from hydrosoft.drivers.errors import DriverError
from hydrosoft.services.bus.config import ConfigError, StackConfig, load_config

UR_TIMEOUT_S = 2.0  # each UR probe, s
DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003


@dataclass
class Probe:
    """One device's answer: ok, what was probed and what came back (or why not), and how long it took (s)."""

    device: str
    ok: bool
    detail: str
    seconds: float


async def _timed(device: str, probe) -> Probe:
    tic = time.monotonic()
    try:
        detail = await probe
        return Probe(device, True, detail, time.monotonic() - tic)
    except (DriverError, OSError, TimeoutError, ValueError) as err:
        return Probe(device, False, str(err), time.monotonic() - tic)


async def _ur(host: str) -> str:
    from hydrosoft.drivers.ur.probe import probe_port, probe_rtde_stream

    await probe_port(host, DASHBOARD_PORT, "dashboard", UR_TIMEOUT_S)
    await probe_port(host, SCRIPT_PORT, "script", UR_TIMEOUT_S)
    await probe_rtde_stream(host, UR_TIMEOUT_S)
    return f"{host}: dashboard and script ports open, RTDE streams"


async def _ft300(port: str) -> str:
    from hydrosoft.drivers.robotiq_ft300.config import FT300Config
    from hydrosoft.drivers.robotiq_ft300.sensor import FT300Sensor

    if not port:
        raise ValueError("no ft_port configured for this arm")
    sensor = FT300Sensor(FT300Config(port=port))
    await sensor.connect()
    try:
        sample = await sensor.read()
    finally:
        await sensor.close()
    force = ", ".join(f"{v:.2f}" for v in sample.wrench[:3])
    return f"{port}: streaming, force [{force}] N"


async def _camera(config: StackConfig) -> str:
    from hydrosoft.drivers.camera.config import OpenCVCameraConfig
    from hydrosoft.drivers.camera.opencv import OpenCVCamera

    source = int(config.camera.device) if config.camera.device.isdigit() else config.camera.device
    camera = OpenCVCamera(OpenCVCameraConfig(source=source, width=config.camera.width, height=config.camera.height,
                                             fps=config.camera.fps))
    await camera.connect()
    try:
        frame = await camera.read()
    finally:
        await camera.close()
    return f"{source}: frame {frame.image.shape[1]}x{frame.image.shape[0]}"


async def _calibration(config: StackConfig) -> str:
    from hydrosoft.drivers.camera.config import load_calibration

    if not config.camera.calibration:
        raise ValueError("camera.calibration is not set: the lab's tag camera needs its calibration file")
    calibration = load_calibration(config.camera.calibration, require_extrinsics=True)
    i = calibration.intrinsics
    return f"{config.camera.calibration}: {i.width}x{i.height} px, fx {i.fx:.1f} px, T_base_camera set"


async def _depth(config: StackConfig, arm: str) -> str:
    from hydrosoft.services.bubble_camera import BubbleDepth, lab_depth_camera

    try:
        camera = lab_depth_camera(config, arm)
        BubbleDepth.captured(config, arm)
    except ConfigError as err:
        raise ValueError(str(err)) from err
    await camera.connect()
    try:
        frame = await camera.read()
    finally:
        await camera.close()
    depth = config.arm(arm).depth
    return (f"{depth.device}: frame {frame.depth.shape[1]}x{frame.depth.shape[0]} uint16; reference "
            f"{depth.reference} loads")


async def check(config: StackConfig) -> list[Probe]:
    """Probe every device of ``config`` (never the arm's motion)."""
    probes = []
    for arm in config.arms:
        probes.append(await _timed(f"ur {arm.name}", _ur(arm.ur_host)))
        probes.append(await _timed(f"ft300 {arm.name}", _ft300(arm.ft_port)))
        probes.append(await _timed(f"depth {arm.name}", _depth(config, arm.name)) if config.mode == "lab"
                      else Probe(f"depth {arm.name}", True, "rendered by sim_world", 0.0))
    if config.mode == "lab":
        probes.append(await _timed("tag camera", _camera(config)) if config.camera.device
                      else Probe("tag camera", False, "camera.device is not set", 0.0))
        probes.append(await _timed("calibration", _calibration(config)))
    else:
        probes.append(Probe("tag camera", True, "rendered by sim_world", 0.0))
    return probes


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="the stack's TOML config (deploy/lab.toml, deploy/sim.toml)")
    parser.add_argument("--json", action="store_true", help="print one JSON document")


def run(args: argparse.Namespace) -> int:
    try:
        config = load_config(args.config)
    except ConfigError as err:
        print(f"hydrosoft-stack check: {err}", file=sys.stderr)
        return 2
    probes = asyncio.run(check(config))
    if args.json:
        print(json.dumps({"devices": [asdict(p) for p in probes]}))
    else:
        for p in probes:
            print(f"{'ok  ' if p.ok else 'FAIL'} {p.device:<16} {p.detail} ({p.seconds:.2f} s)")
    return 0 if all(p.ok for p in probes) else 1
