"""The ``hydrosoft-stack`` command line.

Subcommands import their implementation lazily, so ``--help`` is fast and ``demo`` needs no benchmark code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from hydrosoft.services.bus.allocator import reexec_with_allocator

# group -> (group help, {subcommand -> (module with add_arguments(parser) and run(args) -> int, one-line help)})
GROUPS = {
    "bench": ("benchmarks that print figures (see `bench COMMAND --help`)", {
        "model": ("hydrosoft.bench.model", "contact-model step time, throughput, memory and force accuracy per model, dtype, batch and point count"),
        "control": ("hydrosoft.bench.control", "closed/open-loop MPC error per task and model (paper Table III, simulation)"),
        "tradeoff": ("hydrosoft.bench.tradeoff", "solve time against closed-loop error over the planner's knobs"),
        "bus": ("hydrosoft.services.benchmarks.bus", "one-way bus latency between two processes: wrench and 640x480 depth frames over tcp loopback and ipc"),
        "tracker": ("hydrosoft.services.benchmarks.tracker", "AprilTag tracker accuracy on rendered images: position/orientation error and detection rate per camera distance and view angle"),
        "plant": ("hydrosoft.services.benchmarks.plant", "one sim_world physics tick, eager against compiled (sim.compile), on a config's plant"),
        "soak": ("hydrosoft.services.benchmarks.soak", "the sim stack idle (CPU per service), then goals back to back for minutes: memory, CPU and the camera-to-target latency split, first against last window. Runs the stack's start (minutes: the paper planner compiles; run `compile CONFIG` first) plus --idle-seconds plus --minutes"),
        "recording": ("hydrosoft.services.benchmarks.recording", "the sim stack's plan rate and bus latency without, with and again without a recorder attached, in one run"),
        "fit": ("hydrosoft.bench.fit_noise", "the material fit on synthetic recordings of a known material: recovery, and coverage of its 95-percent intervals under FT 300 noise over 10 seeds (about 2 min of CPU; 2-12 min of wall time on a 2-core machine, longer when it is loaded)"),
        "wrench": ("hydrosoft.bench.wrench", "wrench RMSE per object and contact model on collected recordings (paper Table II)"),
    }),
    "collect": ("record benchmark data with the arm (see `collect DATASET --help`)", {"wrench": ("hydrosoft.services.commands.collect", "press-and-shear trajectories on the benchmark objects: bubble pose, object pose and F/T wrench to MCAP (paper Table II)")}),
    "simulate": ("run a simulated device on its own until Ctrl-C (see `simulate DEVICE --help`)", {
        "ur": ("hydrosoft.drivers.ur.simulator", "simulated UR e-Series controller (RTDE 30004, dashboard 29999, script 30003) on a 127.0.0.N address"),
        "ft300": ("hydrosoft.drivers.robotiq_ft300.simulator", "simulated Robotiq FT 300 streaming real frames on a pseudo-terminal"),
    }),
    "calibrate": ("calibrate a device (see `calibrate DEVICE --help`)", {
        "camera": ("hydrosoft.drivers.camera.calibration", "camera intrinsics from ChArUco board pictures, written as a calibration TOML"),
        "task-frame": ("hydrosoft.services.commands.calibrate", "the task scene's frame in the robot base frame (scene.task_frame), from the tag tracker's poses of the object set down where the task starts"),
    }),
    "ft": ("the F/T sensors of a running stack (see `ft COMMAND --help`)", {
        "tare": ("hydrosoft.services.commands.ft", "tare an arm's F/T sensor now (refused unless the arm is at rest and its bubble touches nothing); the bias is stored and kept across restarts"),
    }),
    "arm": ("act on a running stack's arm (see `arm ACTION --help`)", {
        "enable": ("hydrosoft.services.commands.arm", "re-enable an arm after an external stop (pendant, dashboard, protective, safeguard or emergency stop): refused while the controller still reports one"),
    }),
    "keys": ("CURVE keys for a stack split across hosts (see `keys generate --help`)", {"generate": ("hydrosoft.services.commands.keys", "write a host's CURVE key pair: DIR/HOST.key (public, for its peers' authorized_keys_dir) and DIR/HOST.key_secret (mode 0600)")}),
    "capture": ("capture what a device needs before a run (see `capture WHAT --help`)", {
        "reference": ("hydrosoft.services.commands.capture", "a Soft Bubble's reference membrane (its undeformed depth image, the median of N frames) for lab mode, as a .npz file"),
    }),
}


# top-level command -> (module with add_arguments(parser) and run(args) -> int, one-line help)
COMMANDS = {
    "goal": ("hydrosoft.services.client", "set a goal on a running stack, start it and (with --wait) wait for the outcome"),
    "launch": ("hydrosoft.services.commands.launch", "start the stack's services from a config, keep them up, stop them safely on Ctrl-C"),
    "status": ("hydrosoft.services.commands.status", "show each running service's state, pid, uptime, message rates, restarts and errors"),
    "compile": ("hydrosoft.services.commands.compile", "build the artefacts of a config's compiled plant and planner once (torch's compile cache), so that every launch after it loads them"),
    "check": ("hydrosoft.services.commands.check", "probe every device a stack config names and say what answers, without moving the arm"),
    "replay": ("hydrosoft.services.commands.replay", "publish an MCAP recording back onto the bus with its original timing (stands in for the services that sent it)"),
    "view": ("hydrosoft.services.commands.view", "serve a running stack's scene and topics live to Foxglove over WebSocket on 127.0.0.1"),
    "fit": ("hydrosoft.bench.fit", "the Soft Bubble's material (E, K, mu) fitted to collect-wrench recordings, with its uncertainty and held-out RMSE, as TOML for a scene"),
    "plot": ("hydrosoft.services.commands.plot", "PNG plots of a recorded run: object error, contact forces, planner solve time and rate, watchdog events"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hydrosoft-stack",
        description="ROS-free control stack for compliant tactile manipulation with non-holonomic hydroelastic "
        "contact models (Hydrosoft).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser(
        "demo",
        help="run a short simulated planar-pushing rollout and print what happened",
        description="Compile the planar pushing scene, drag the cube with the bubble for a few steps and print the "
        "object's motion and the contact forces at each step. Needs no hardware.",
    )
    demo.add_argument("--steps", type=int, default=20, help="control steps to simulate (default 20)")
    demo.add_argument("--model", default="nh", choices=["nh", "snh", "pf", "pff"], help="contact model (default nh)")
    demo.add_argument("--speed", type=float, default=2.0, help="bubble speed along x in mm per step (default 2)")
    for name, (module, text) in COMMANDS.items():
        p = sub.add_parser(name, help=text, description=text)
        p.set_defaults(command_module=module)
        importlib.import_module(module).add_arguments(p)
    for group, (group_help, commands) in GROUPS.items():
        group_parser = sub.add_parser(group, help=group_help)
        group_sub = group_parser.add_subparsers(dest=group, metavar=group.upper(), required=True)
        for name, (module, text) in commands.items():
            p = group_sub.add_parser(name, help=text, description=text)
            p.set_defaults(command_module=module)
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    if args.command == "demo":
        from hydrosoft.services.commands.demo import run_demo

        return run_demo(steps=args.steps, model=args.model, speed_mm=args.speed)
    return importlib.import_module(args.command_module).run(args)


def entry() -> None:
    """The ``hydrosoft-stack`` script: ``main`` on the faster allocator when one is installed (``allocator``)."""
    reexec_with_allocator()
    sys.exit(main())


if __name__ == "__main__":
    entry()
