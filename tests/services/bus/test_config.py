"""The stack config: the shipped files load, bad keys are named, endpoints stay local without CURVE keys."""

from __future__ import annotations

import os
from pathlib import Path

import msgspec
import pytest

from hydrosoft.services.bus.config import (PLANNER_PRESETS, SDF_SOLVER_STEPS_MAX, ConfigError, PlannerConfig,
                                          load_config, parse_config)
from hydrosoft.services.bus.service_cli import CACHE_ENV, use_compile_cache

DEPLOY = Path(__file__).parents[3] / "deploy"
ONE_ARM = 'arms = [{ name = "bubble" }]\n'


@pytest.mark.parametrize("name", ["sim.toml", "sim-bimanual.toml"])
def test_the_shipped_configs_load(name):
    config = load_config(DEPLOY / name)
    names = config.service_names()
    assert names[0] == "sim_world" and names[-1] == "planner"
    assert all(f"arm_commander-{arm.name}" in names for arm in config.arms)
    assert config.endpoint("planner", "cmd").startswith("ipc://")


@pytest.mark.parametrize("text, key", [
    (ONE_ARM + "[limits]\nmax_speed_m_s = 0\n", "limits.max_speed_m_s"),
    (ONE_ARM + "[limits]\nworkspace_min = [0.2, 0, 0]\n", "limits.workspace_min"),
    (ONE_ARM + "[limits]\nidle_rate_hz = 200\n", "limits.idle_rate_hz"),  # above the servo rate
    (ONE_ARM + "colour = 1\n", "colour"),
    (ONE_ARM + "[planner]\nheartbeat_period_s = 0.3\n", "planner.heartbeat_period_s"),
    (ONE_ARM + "[services.nope]\nrestart = \"always\"\n", "services.nope"),
    (ONE_ARM + "[sim]\nrate_hz = 20\n", "sim.rate_hz"),
    (ONE_ARM + "[camera]\ndetector_threads = 0\n", "camera.detector_threads"),
    (ONE_ARM + "[sim]\nur_tick_hz = 100\n", "sim.ur_tick_hz"),  # below the servo rate
    (ONE_ARM + "[scene]\ntask_frame = [0.5, 0, 0, 0.9, 0, 0, 0.1]\n", "scene.task_frame"),  # not unit length
    (ONE_ARM + "[scene]\ntask_frame = [0.5, 0, 0, 0.995, 0.0998, 0, 0]\n", "scene.task_frame"),  # 11.5 deg tilt
    ('arms = [{ name = "a" }, { name = "a" }]\n', "arms"),
    (ONE_ARM + "[planner]\nsdf_solver_steps = 33\n", "planner.sdf_solver_steps"),
    (ONE_ARM + "[planner]\nworkers = 0\n", "planner.workers"),
    (ONE_ARM + "[planner]\nnice = 20\n", "planner.nice"),
    (ONE_ARM + "[planner]\nstall_s = 0\n", "planner.stall_s"),
    (ONE_ARM + "[planner]\nstall_s = inf\n", "planner.stall_s"),  # "never" is the goal's timeout, not this key
    (ONE_ARM + "[planner]\ndevice = \"gpu\"\n", "planner.device"),
    (ONE_ARM + "[planner]\ndevice = \"cuda:x\"\n", "planner.device"),
    (ONE_ARM + "[planner]\nsamples = 16\nworkers = 17\n", "planner.workers"),  # more workers than samples
    (ONE_ARM + "[planner]\nobject_update = \"implicit\"\n", "planner.object_update"),
    (ONE_ARM + "[planner]\nmodel = \"pf\"\nobject_update = \"linearly_implicit\"\n", "planner.object_update"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nE = -3e5\n', "arms.bubble.material.E"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nE = inf\n', "arms.bubble.material.E"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nK = nan\n', "arms.bubble.material.K"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nK = 0\n', "arms.bubble.material.K"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nmu = 3.5\n', "arms.bubble.material.mu"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nmu = -0.1\n', "arms.bubble.material.mu"),
    ('[[arms]]\nname = "bubble"\n[arms.material]\nG = 1e5\n', "unknown field `G`"),
])
def test_a_bad_key_is_named(text, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        parse_config(text, "test.toml")


def test_the_planner_device_is_the_cpu_unless_a_gpu_is_named():
    assert parse_config(ONE_ARM, "test.toml").planner.device == "cpu"
    for device in ("cpu", "cuda", "cuda:1"):
        assert parse_config(ONE_ARM + f'[planner]\ndevice = "{device}"\n', "test.toml").planner.device == device


def test_a_non_local_endpoint_needs_curve_keys():
    with pytest.raises(ConfigError, match="endpoints.planner.data.*CURVE"):
        parse_config(ONE_ARM + '[endpoints]\n"planner.data" = "tcp://0.0.0.0:5555"\n', "test.toml")
    config = parse_config(ONE_ARM + '[endpoints]\n"planner.data" = "tcp://127.0.0.1:5555"\n', "test.toml")
    assert config.endpoint("planner") == "tcp://127.0.0.1:5555"


def test_per_arm_service_names():
    config = parse_config(ONE_ARM, "test.toml")
    assert config.arm_service("ft_reader", None) == ("ft_reader-bubble", "bubble")
    with pytest.raises(ConfigError, match="expected ft_reader-ARM"):
        config.arm_service("ft_reader", "planner")
    with pytest.raises(ConfigError, match="no arm named 'left'"):
        config.arm_service("ft_reader", "ft_reader-left")


def test_a_level_task_frame_is_taken_and_a_tilted_one_named_with_its_tilt():
    turned = parse_config(ONE_ARM + "[scene]\ntask_frame = [0.5, -0.1, -0.02, 0.0, 0.0, 0.0, 1.0]\n", "test.toml")
    assert turned.scene.task_frame == (0.5, -0.1, -0.02, 0.0, 0.0, 0.0, 1.0)  # 180 deg about z is level
    assert parse_config(ONE_ARM, "test.toml").scene.task_frame == (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    with pytest.raises(ConfigError, match=r"scene\.task_frame: its z axis is 180\.0 deg .*\[qw, qx, qy, qz\] order"):
        parse_config(ONE_ARM + "[scene]\ntask_frame = [0.5, 0, 0, 0.0, 0.0, 1.0, 0.0]\n", "test.toml")  # 180 about y


def test_the_sdf_step_bound_is_the_ellipsoids():
    """config.py names the bound without importing torch; it must be the ellipsoid's own."""
    from hydrosoft.geometry.sdf import Ellipsoid
    assert SDF_SOLVER_STEPS_MAX == Ellipsoid.MAX_SOLVER_STEPS
    assert parse_config(ONE_ARM + f"[planner]\nsdf_solver_steps = {SDF_SOLVER_STEPS_MAX}\n").planner.sdf_solver_steps \
        == SDF_SOLVER_STEPS_MAX


def test_the_compile_cache_goes_to_the_config_dir_unless_the_environment_names_one(monkeypatch, tmp_path):
    config = parse_config(ONE_ARM + f'compile_cache_dir = "{tmp_path}/torch"\n')
    monkeypatch.setenv(CACHE_ENV, "placeholder")  # records the variable's state before the test, restored after
    monkeypatch.delenv(CACHE_ENV)
    use_compile_cache(parse_config(ONE_ARM))  # no key: torch's default stays
    assert CACHE_ENV not in os.environ
    use_compile_cache(config)
    assert os.environ[CACHE_ENV] == f"{tmp_path}/torch"
    monkeypatch.setenv(CACHE_ENV, "/elsewhere")
    use_compile_cache(config)
    assert os.environ[CACHE_ENV] == "/elsewhere"
    monkeypatch.delenv(CACHE_ENV)
    use_compile_cache(parse_config(ONE_ARM + 'compile_cache_dir = "~/cache"\n'))
    assert os.environ[CACHE_ENV] == str(Path("~/cache").expanduser())


def test_state_dir_lies_under_run_dir_unless_absolute_and_sim_ft_bias_is_checked():
    base = 'run_dir = "/run/hydrosoft"\n[[arms]]\nname = "bubble"\n'
    assert parse_config(base).state_path() == Path("/run/hydrosoft/state")
    assert parse_config('state_dir = "/var/lib/hydrosoft"\n' + base).state_path() == Path("/var/lib/hydrosoft")
    assert parse_config('state_dir = "tares"\n' + base).state_path() == Path("/run/hydrosoft/tares")
    assert parse_config(base).sim.ft_bias == (0.0,) * 6
    assert parse_config(base + '[sim]\nft_bias = [1, 2, 3, 0.1, 0.2, 0.3]\n').sim.ft_bias == (1, 2, 3, 0.1, 0.2, 0.3)
    for bad in ("[1, 2, 3]", "[1, 2, 3, 0, 0, nan]", "[101, 0, 0, 0, 0, 0]", "[0, 0, 0, 0, 0, -11]"):
        with pytest.raises(ConfigError, match="sim.ft_bias"):
            parse_config(base + f"[sim]\nft_bias = {bad}\n")


TWO_HOSTS = ONE_ARM + '''
[curve]
secret_key_file = "/keys/shared.key_secret"
authorized_keys_dir = "/keys/authorized"

[hosts.robot]
address = "10.0.0.2"
services = ["sim_world", "arm_commander-bubble", "ft_reader-bubble", "bubble_camera-bubble", "tag_tracker"]
public_key_file = "/keys/robot.key"
secret_key_file = "/keys/robot.key_secret"
run_dir = "/run/robot"

[hosts.compute]
address = "10.0.0.3"
services = ["planner"]
first_port = 7000
public_key_file = "/keys/compute.key"
'''


def test_a_split_stack_reads_its_own_hosts_services_over_ipc_and_the_others_over_tcp_on_fixed_ports():
    config = parse_config(TWO_HOSTS, "test.toml")
    assert config.host_of("planner") == "compute" and config.host_of("tag_tracker") == "robot"
    planner_index = config.service_names().index("planner")
    assert config.endpoint("planner", "cmd") == f"tcp://10.0.0.3:{7000 + 3 * planner_index + 2}"
    assert config.endpoint("sim_world", "data") == "tcp://10.0.0.2:5600"  # no host named: every service over tcp
    robot = config.on_host("robot")
    assert robot.run_dir == "/run/robot" and robot.curve.secret_key_file == "/keys/robot.key_secret"
    assert robot.local_services() == config.hosts["robot"].services
    assert robot.endpoint("sim_world", "status") == "ipc:///run/robot/sim_world.status"
    assert robot.endpoint("planner", "data") == config.tcp_endpoint("planner", "data")
    runtime = robot.runtime("sim_world")
    assert runtime.also_bind["ipc:///run/robot/sim_world.status"] == "tcp://10.0.0.2:5601"
    assert runtime.curve.server_key_files[config.tcp_endpoint("planner", "cmd")] == Path("/keys/compute.key")
    compute = config.on_host("compute")
    assert compute.run_dir == config.run_dir and compute.curve.secret_key_file == "/keys/shared.key_secret"
    assert compute.local_services() == ["planner"] and compute.endpoint("planner").startswith("ipc://")
    assert len({config.tcp_endpoint(name, kind) for name in config.service_names()
                for kind in ("data", "status", "cmd")}) == 3 * len(config.service_names())
    with pytest.raises(ConfigError, match=r"--host.*no host 'laptop'"):
        config.on_host("laptop")


@pytest.mark.parametrize("change, key", [
    (('services = ["planner"]', 'services = ["planner", "tag_tracker"]'), r"hosts\.compute\.services.*also on"),
    (('services = ["planner"]', 'services = []'), r"hosts: .*planner"),
    (('services = ["planner"]', 'services = ["planer"]'), r"hosts\.compute\.services.*no service 'planer'"),
    (('address = "10.0.0.3"', 'address = "compute.lab"'), r"hosts\.compute\.address"),
    (("first_port = 7000", "first_port = 65530"), r"hosts\.compute\.first_port"),
])
def test_a_bad_host_table_is_named(change, key):
    with pytest.raises(ConfigError, match=key):
        parse_config(TWO_HOSTS.replace(*change), "test.toml")


def test_hosts_beyond_loopback_need_curve_keys():
    text = TWO_HOSTS.split("[curve]")[0] + "[hosts" + TWO_HOSTS.split("[hosts", 1)[1]
    with pytest.raises(ConfigError, match=r"hosts\.robot: .*CURVE"):
        parse_config(text, "test.toml")


def test_a_fitted_material_pasted_below_an_arm_reaches_the_planners_and_the_plants_models(tmp_path):
    from hydrosoft.bench.fit import params_toml
    from hydrosoft.scene import compile_scene
    from hydrosoft.services.planner import planner_scene
    from hydrosoft.services.sim_world import plant_model
    from hydrosoft.tasks import make_task

    document = {"model": "nh", "uncertainty_method": "hessian", "bootstrap": None, "settings": {"objects": ["cube"]},
                "split": {"fit": [["cube", 0]], "held_out": []},
                "rows": [{"set": "held_out", "when": "after", "trajectories": 0}],
                "parameters": {"E": {"value": 5.1e5, "sigma": 700.0, "interval95": [5.08e5, 5.12e5], "unit": "Pa/m",
                                     "fitted": True, "identified": True},
                               "K": {"value": 6e4, "sigma": 9e4, "interval95": [1e3, 9e5], "unit": "Pa/m",
                                     "fitted": True, "identified": False},
                               "mu": {"value": 0.35, "sigma": 0.02, "interval95": [0.31, 0.39], "unit": "",
                                      "fitted": True, "identified": True}}}
    shipped = (DEPLOY / "sim.toml").read_text()
    arm_keys_end = shipped.index("\n\n", shipped.index("[[arms]]"))  # the end of the arm's table
    text = shipped[:arm_keys_end] + "\n" + params_toml(document) + shipped[arm_keys_end:]
    (tmp_path / "fitted.toml").write_text(text)
    config = load_config(tmp_path / "fitted.toml")
    assert config.bubble_materials() == {"bubble": {"E": 5.1e5, "mu": 0.35}}  # K not identified: the scene's
    task = make_task(config.scene.task)
    planner, _, _ = compile_scene(planner_scene(task, config))
    plant, _ = plant_model(config)
    for model in (planner, plant):
        bubble, table = model.body_names.index("bubble"), model.body_names.index("table")
        assert float(model.material.E[bubble]) == 5.1e5 and float(model.material.mu[bubble]) == 0.35
        assert float(model.material.K[bubble]) == 1e5 and float(model.material.E[table]) == 1e6
    plain, _ = plant_model(load_config(DEPLOY / "sim.toml"))
    assert float(plain.material.E[plain.body_names.index("bubble")]) == 3e5

def test_the_planner_cuts_its_samples_into_chunks_from_its_workers_to_its_samples():
    """``planner.chunks``: the paper preset shares its 64 samples out in chunks; 0 (the default) is one chunk per
    worker; a count below the workers or above the samples is refused by name."""
    assert parse_config(ONE_ARM + '[planner]\npreset = "paper"\n').planner.chunks == PLANNER_PRESETS["paper"]["chunks"]
    assert PlannerConfig().chunks == 0
    assert parse_config(ONE_ARM + '[planner]\nworkers = 2\nchunks = 16\n').planner.chunks == 16
    for chunks in (1, 17):
        with pytest.raises(ConfigError, match="planner.chunks: must be 0 .* or from planner.workers"):
            parse_config(ONE_ARM + f'[planner]\nworkers = 2\nchunks = {chunks}\n', "test.toml")


def test_a_planner_preset_fills_the_planner_and_its_own_keys_override_it():
    paper = parse_config(ONE_ARM + '[planner]\npreset = "paper"\n').planner
    assert (paper.samples, paper.horizon, paper.grad_steps, paper.dtype, paper.compile) == (64, 10, 2, "float32", True)
    assert paper.preset == "paper" and paper.workers == 2 and paper.worker_processes and paper.nice == 10
    assert paper == msgspec.convert({**PLANNER_PRESETS["paper"], "preset": "paper"}, PlannerConfig)
    quick = parse_config(ONE_ARM + '[planner]\npreset = "quick"\nsamples = 32\ncompile = true\n').planner
    assert (quick.samples, quick.horizon, quick.grad_steps, quick.compile) == (32, 6, 1, True)  # the keys win
    assert parse_config(ONE_ARM).planner == PlannerConfig()  # no preset: the defaults
    with pytest.raises(ConfigError, match="planner.preset: must be one of paper, quick"):
        parse_config(ONE_ARM + '[planner]\npreset = "fast"\n', "test.toml")
    with pytest.raises(ConfigError, match="planner.workers"):  # a preset's values are checked as the keys are
        parse_config(ONE_ARM + '[planner]\npreset = "paper"\nsamples = 1\n', "test.toml")


def test_deploy_sim_toml_runs_the_paper_planner_and_waits_for_its_compile():
    config = load_config(DEPLOY / "sim.toml")
    assert config.planner.preset == "paper" and config.planner.samples == 64 and config.planner.compile
    assert config.planner.target_lead_s <= config.limits.max_target_lead_s
    assert config.service("planner").ready_timeout_s >= 300.0  # a cold compile on 2 busy cores takes minutes


def test_sim_ft_noise_is_off_unless_set_the_sim_configs_set_the_datasheets_and_bad_values_are_refused():
    base = 'run_dir = "/run/hydrosoft"\n[[arms]]\nname = "bubble"\n'
    assert parse_config(base).sim.ft_noise == 0.0
    assert parse_config(base + "[sim]\nft_noise = 2.5\n").sim.ft_noise == 2.5
    for deployed in ("sim.toml", "sim-bimanual.toml"):
        assert load_config(Path(__file__).parents[3] / "deploy" / deployed).sim.ft_noise == 1.0
    for bad in ("-0.5", "nan", "11"):
        with pytest.raises(ConfigError, match="sim.ft_noise"):
            parse_config(base + f"[sim]\nft_noise = {bad}\n")
