"""The bus processes: `xneck bridge --driver beaglebone|twin|replay`, `xneck twin` and
`xneck controller`.

This is where the layers meet: the bridge node (:mod:`bridge.node`) is given its driver (the
twin's comes from :mod:`twin.sim.driver`) and its hold rule (:func:`controller.laws.encoder_hold_forces`)
here, so the bridge package itself depends on neither. Heavy imports stay inside the commands:
`xneck --help` and the bridge on a small board load only what they run.
"""

from __future__ import annotations

import logging
import re
import socket
import tomllib
from pathlib import Path

import typer

from bridge import toml_text
from server.cli.options import (
    ALPHA_IP_OPTION,
    AUTOCONNECT_OPTION,
    CABLE_MODEL_OPTION,
    CONNECT_OPTION,
    IDLE_TIMEOUT_OPTION,
    INSTANCE_OPTION,
    LAW_OPTION,
    LISTEN_OPTION,
    LOCKSTEP_OPTION,
    MAX_TICKS_OPTION,
    NO_FRICTION_OPTION,
    NO_PULLEYS_OPTION,
    NON_NEGATIVE,
    PARAMS_OPTION,
    POSITIVE,
    SEED_OPTION,
    SET_OPTION,
    STARTUP_TIMEOUT_OPTION,
    TRAJECTORY_OPTION,
    TRUTH_OPTION,
    VERBOSE_OPTION,
    check_credentials,
    check_endpoints,
    fail,
    law_config,
    load_checked_trajectory,
    load_cli_params,
    open_bus,
)

log = logging.getLogger("xneck.bridge")

# Off when `xneck camera --source twin` measures α_IP on rendered frames instead (issue 15).
NO_CAMERA_OPTION = typer.Option(False, "--no-camera", help="Twin: publish no white-noise α_IP (for `xneck camera --source twin`).")


def bridge_node(session, driver, params, config):
    """A :class:`bridge.node.BridgeNode` for a parameter set: the bridge's safety rules with the
    force range of ``params`` and the controller's hold rule (θ → hold forces). The one place
    where the bridge is composed with the model; ``xneck bridge`` and in-process tests use it."""
    from bridge.node import BridgeNode
    from controller.laws import encoder_hold_forces

    if driver.n_motors != params.n_cables:
        raise ValueError(f"the driver has {driver.n_motors} motors, the parameter set {params.n_cables} cables")
    return BridgeNode(session, driver, encoder_hold_forces(params), (params.limits.f_min, params.limits.f_max), config)


def _driver_table(path: Path | None) -> dict:
    if path is None:
        return {}
    try:
        return toml_text.loads(path.read_text())
    except OSError as exc:
        raise fail(f"{path}: cannot read the driver config ({exc.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise fail(f"{path}: not a valid TOML file ({exc})") from None


def make_driver(driver: str, params, table: dict, *, replay: Path | None = None, loop: bool = False,
                seed: int = 0, cable_model: str | None = None, friction: bool = True,
                truth: str = "model", camera: bool = True, alpha_ip: str = "noise"):
    """The driver named ``driver`` with its config from ``table`` (a TOML table) and the options.
    Raises :class:`bridge.driver.DriverError` with a readable reason."""
    from bridge.driver import DriverError, config_from_dict

    base = {"n_motors": params.n_cables, **table}
    if driver == "beaglebone":
        from bridge.drivers.beaglebone import BeagleBoneConfig, BeagleBoneDriver

        return BeagleBoneDriver.from_params(config_from_dict(BeagleBoneConfig, base), params)
    if driver == "twin":
        from twin.sim.driver import TwinDriver, TwinDriverConfig

        base.setdefault("seed", seed)
        if cable_model is not None:
            base["cable_model"] = cable_model
        if not friction:
            base["friction"] = False
        if truth != "model":
            base["truth"] = truth
        if not camera:
            base["camera"] = False
        if alpha_ip != "noise":
            base["alpha_ip"] = alpha_ip
        return TwinDriver(config_from_dict(TwinDriverConfig, base), params)
    if driver == "replay":
        from bridge.drivers.replay import ReplayConfig, ReplayDriver

        if replay is None and "path" not in table:
            raise DriverError("--driver replay needs --replay FILE (a campaign MCAP file)")
        if replay is not None:
            base["path"] = str(replay)
        base.setdefault("loop", loop)
        return ReplayDriver(config_from_dict(ReplayConfig, base))
    raise DriverError(f"unknown driver {driver!r}: choose beaglebone, twin or replay")


def _drives_off(driver: str, driver_config: Path | None, params_file: Path | None, overrides: list[str] | None) -> None:
    """``xneck bridge --drives-off``: a bridge killed by SIGKILL (the OOM killer, a supervisor
    giving up on a hung one) cannot run its own shutdown, and the ESCONs go on driving the last
    current with their enable lines high. Configuring the driver sets every drive off first
    (:meth:`bridge.drivers.beaglebone.BeagleBoneDriver._on_configure`); closing it keeps them off."""
    from bridge.driver import DriverError

    if driver != "beaglebone":
        raise fail(f"--drives-off is for --driver beaglebone (the {driver} driver drives no motors)")
    params = load_cli_params(params_file, overrides)
    try:
        drv = make_driver(driver, params, _driver_table(driver_config))
        from bridge.drivers.beaglebone import BeagleBoneDriver

        if isinstance(drv, BeagleBoneDriver):
            drv.exclusive = False  # an off switch, also beside a running bridge (bridge.drivers.board_lock)
        drv.configure()
    except (DriverError, ValueError) as exc:  # the reason says whether the lines were switched off
        raise fail(f"--drives-off: {exc}") from None
    drv.close()  # disables them once more, and must say so
    if drv.close_error:
        raise fail(f"could not disable the drives: {drv.close_error}")
    log.info("bridge --drives-off: every drive disabled (enable lines off, zero-current set values)")


def default_instance(driver: str, hostname: str | None = None) -> str:
    """The bridge's name on the bus when ``--instance`` is not given: ``beaglebone-<hostname>`` for
    the robot's board, the same at each start, so a camera following its clock (docs/camera.md,
    "One clock") and the console know it again after systemd restarts it (a random name made the
    camera refuse the restarted bridge as foreign); "" (a random name) for the twin and replays,
    of which one machine may run several."""
    if driver != "beaglebone":
        return ""
    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", hostname if hostname is not None else socket.gethostname())
    return f"beaglebone-{host or 'board'}"[:64]


def latch_path(option: str | None, driver: str) -> Path | None:
    """The e-stop latch file of ``--estop-latch`` (bridge.estop_latch): the board's default for
    ``--driver beaglebone`` when not given, none for the twin and replays (a test machine runs many,
    under random names) and for 'none'."""
    from bridge.estop_latch import default_latch_path

    if option is None:
        return default_latch_path() if driver == "beaglebone" else None
    return None if option.strip().lower() == "none" else Path(option).expanduser()


def default_loop_stall_s(driver: str) -> float:
    """``--loop-stall`` when not given (s): the loop watchdog guards real drives only. On the twin
    a stall is the machine's load, not a motor left driving: twice in full-suite runs on the
    loaded 2-CPU development machine a bridge's loop made no tick for 0.5 s while its watchdog
    thread ran, and the watchdog ended a healthy test stack (Zenoh's threads at the loop's FIFO
    priority: bridge.runtime.raise_loop_thread)."""
    from bridge.loop_watchdog import DEFAULT_STALL_S

    return DEFAULT_STALL_S if driver == "beaglebone" else 0.0


def bridge(
    driver: str = typer.Option(..., "--driver", help="beaglebone (the prototype), twin (simulated) or replay (an archive)."),
    replay: Path | None = typer.Option(None, "--replay", help="Campaign MCAP file to replay (--driver replay)."),
    loop: bool = typer.Option(False, "--loop", help="Replay: start over at the end instead of stopping."),
    driver_config: Path | None = typer.Option(
        None, "--driver-config", help="TOML file of the driver's config (e.g. the BeagleBone wiring and ESCON points)."),
    lockstep: bool = LOCKSTEP_OPTION,
    command_timeout: float = typer.Option(0.010, "--command-timeout", callback=POSITIVE,
                                          help="Hold after this long without a valid command (s)."),
    hold_ramp: float = typer.Option(0.010, "--hold-ramp", callback=NON_NEGATIVE,
                                    help="Ramp to the hold forces over this long (s)."),
    hold_damping: float = typer.Option(
        1.0, "--hold-damping", callback=NON_NEGATIVE,
        help="While holding, damp each motor this much on its speed (N·s/rad at the shaft; 0: off; docs/bridge.md)."),
    max_force_step: float = typer.Option(
        1.0, "--max-force-step", callback=POSITIVE, help="After any enable, ramp the forces at most this much per tick (N)."),
    max_force_rate: float = typer.Option(
        5000.0, "--max-force-rate", callback=POSITIVE,
        help="While active, move the forces at most this fast towards the commands (N/s; 10 N per tick at 500 Hz, the "
        "control law's own bound)."),
    loop_stall: float | None = typer.Option(
        None, "--loop-stall", callback=NON_NEGATIVE,
        help="Real time: when the loop makes no tick for this long while the process runs, disable the drives and "
        "exit with code 70 (s, at least 0.05; 0: off). Default: 0.5 with --driver beaglebone, off for the twin "
        "and replay drivers, which drive no motors."),
    seed: int = SEED_OPTION,
    cable_model: str | None = CABLE_MODEL_OPTION,
    no_friction: bool = NO_FRICTION_OPTION,
    truth: str = TRUTH_OPTION,
    no_camera: bool = NO_CAMERA_OPTION,
    alpha_ip: str = ALPHA_IP_OPTION,
    max_ticks: int | None = MAX_TICKS_OPTION,
    idle_timeout: float | None = IDLE_TIMEOUT_OPTION,
    startup_timeout: float | None = STARTUP_TIMEOUT_OPTION,
    instance: str = INSTANCE_OPTION,
    listen: list[str] | None = LISTEN_OPTION,
    connect: list[str] | None = CONNECT_OPTION,
    autoconnect: bool = AUTOCONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
    estop_latch: str | None = typer.Option(
        None, "--estop-latch", help="File keeping an engaged e-stop across restarts of this bridge (docs/safety.md, "
        "rule 4): a bridge that finds it starts latched until a release. Default: "
        "$XDG_STATE_HOME/xneck/estop-board with --driver beaglebone, none for the twin and replay; 'none': off."),
    drives_off: bool = typer.Option(
        False, "--drives-off", help="Only disable the drives (enable lines off, zero-current set values) and exit, "
        "joining no bus: for after a bridge was killed, which could not (systemd ExecStopPost, xneck up --robot)."),
) -> None:
    """Expose the motor controllers on the bus with the twin's topics, behind the bridge's safety
    rules (clamping, 10 ms watchdog to the hold forces, e-stop, drives disabled on exit)."""
    if driver != "twin":
        # Real and replayed motors need the model only once per hold: plain Python keeps numba,
        # llvmlite and scipy out of the bridge (the BeagleBone has neither the RAM nor the wheels).
        from twin.model.compiled import prefer_plain_python

        prefer_plain_python()
    from bridge.driver import DriverError
    from bridge.instance_check import NameTaken, check_name_free
    from bridge.node import BridgeConfig
    from bridge.runtime import setup_logging, stop_on_signals

    setup_logging(verbose)
    if loop_stall is None:
        loop_stall = default_loop_stall_s(driver)
    if drives_off:
        _drives_off(driver, driver_config, params_file, overrides)
        return
    check_endpoints(listen, connect)  # before the driver is built (the twin's compiles for seconds)
    check_credentials()
    params = load_cli_params(params_file, overrides)
    if lockstep and driver != "twin":
        raise fail("--lockstep needs --driver twin: real motors cannot wait for the controller")
    if no_camera and alpha_ip != "noise":
        # accepted, the twin then published no α_IP at all (user audit of session 45)
        raise fail(f"--no-camera and --alpha-ip {alpha_ip}: the twin's α_IP is off with --no-camera; choose one")
    try:
        config = BridgeConfig(command_timeout_s=command_timeout, hold_ramp_s=hold_ramp, lockstep=lockstep,
                              max_force_step_N=max_force_step, max_force_rate_N_s=max_force_rate,
                              loop_stall_s=loop_stall,
                              idle_timeout_s=idle_timeout, startup_timeout_s=startup_timeout, max_ticks=max_ticks,
                              instance=instance or default_instance(driver), hold_damping_N_s_rad=hold_damping,
                              estop_latch_path=latch_path(estop_latch, driver))
    except ValueError as exc:
        raise fail(str(exc)) from None
    try:
        drv = make_driver(driver, params, _driver_table(driver_config), replay=replay, loop=loop, seed=seed,
                          cable_model=cable_model, friction=not no_friction, truth=truth, camera=not no_camera,
                          alpha_ip=alpha_ip)
        drv.configure()
    except (DriverError, ValueError) as exc:
        raise fail(str(exc)) from None
    try:
        # After configure: importing rcpy installs its own SIGINT/SIGTERM handlers, ours must win.
        stop = stop_on_signals()
        with open_bus(listen, connect, autoconnect) as session:
            try:  # before our own token (bridge.instance_check); a signal ends its wait
                check_name_free(session, config.instance, stop=stop)
                node = None if stop.is_set() else bridge_node(session, drv, params, config)
            except NameTaken as exc:
                raise fail(f"bridge not started, drives left off: {exc}") from None
            except ValueError as exc:
                raise fail(str(exc)) from None
            if node is None:
                log.info("bridge %s not started: stopped by a signal during its name check", config.instance)
            else:
                _run_bridge(node, drv, stop, lockstep, loop_stall, command_timeout)
    finally:
        drv.close()
    if drv.close_error:
        # Not a clean exit: a supervisor (xneck up --robot) runs --drives-off after a non-zero one only.
        raise fail(f"DRIVES MAY BE ON: the bridge could not disable them on exit ({drv.close_error})")


def _run_bridge(node, drv, stop, lockstep: bool, loop_stall: float, command_timeout: float) -> None:
    """``xneck bridge``'s loop once its node is up, to the stop, and its closing line."""
    from bridge.node import run_lockstep, run_realtime
    from bridge.runtime import SystemdNotify, raise_priority

    mode = "lockstep" if lockstep else f"real time, {1 / drv.dt:.0f} Hz, " + (
        f"loop watchdog {loop_stall:g} s" if loop_stall else "no loop watchdog")
    log.info("bridge %s up: driver %s (%s), command timeout %.0f ms", node.instance, drv.name, mode,
             command_timeout * 1e3)
    if not lockstep:
        raise_priority()
    try:
        ticks = run_lockstep(node, stop) if lockstep else run_realtime(node, stop, SystemdNotify.from_environ())
    finally:
        node.shutdown(getattr(stop, "cause", ""))
    stats = node.commands.stats
    log.info("bridge %s stopped after %d ticks, %s; commands accepted %d, rejected %d, "
             "clamped %d, holds %d, overruns %d, periods skipped %d", node.instance, ticks,
             "DRIVES MAY BE ON" if drv.close_error else "drives disabled", stats.accepted, stats.rejected,
             node.clamped, node.holds, node.overruns, node.periods_skipped)


def twin(
    ctx: typer.Context,
    lockstep: bool = LOCKSTEP_OPTION,
    seed: int = SEED_OPTION,
    cable_model: str | None = CABLE_MODEL_OPTION,
    no_friction: bool = NO_FRICTION_OPTION,
    truth: str = TRUTH_OPTION,
    no_camera: bool = NO_CAMERA_OPTION,
    alpha_ip: str = ALPHA_IP_OPTION,
    max_ticks: int | None = MAX_TICKS_OPTION,
    idle_timeout: float | None = IDLE_TIMEOUT_OPTION,
    startup_timeout: float | None = STARTUP_TIMEOUT_OPTION,
    instance: str = INSTANCE_OPTION,
    listen: list[str] | None = LISTEN_OPTION,
    connect: list[str] | None = CONNECT_OPTION,
    autoconnect: bool = AUTOCONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Run the simulated robot on the bus: the bridge with the twin as its driver, so it speaks
    exactly the bridge's topics and applies the bridge's safety rules (`xneck bridge --driver twin`).
    `xneck twin calibrate` fits a truth to recorded campaigns instead."""
    if ctx.invoked_subcommand is not None:
        return  # a subcommand (calibrate) runs instead of the twin
    bridge(driver="twin", replay=None, loop=False, driver_config=None, lockstep=lockstep, command_timeout=0.010,
           hold_ramp=0.010, hold_damping=1.0, max_force_step=1.0, max_force_rate=5000.0, loop_stall=None, seed=seed, cable_model=cable_model, no_friction=no_friction, truth=truth, no_camera=no_camera, alpha_ip=alpha_ip, max_ticks=max_ticks,
           idle_timeout=idle_timeout, startup_timeout=startup_timeout, instance=instance, listen=listen,
           connect=connect, autoconnect=autoconnect, params_file=params_file, overrides=overrides, verbose=verbose, drives_off=False, estop_latch=None)


def _check_campaign_kind(value: str) -> str:
    """Typer callback: ``--campaign-kind`` is a bus.CampaignKind (it had no help and took any word)."""
    from typing import get_args

    from bridge.bus import CampaignKind

    if value not in get_args(CampaignKind):
        raise fail(f"--campaign-kind {value!r}: choose {', '.join(get_args(CampaignKind))}")
    return value


def controller(
    law: int = LAW_OPTION,
    no_pulleys: bool = NO_PULLEYS_OPTION,
    trajectory: str | None = TRAJECTORY_OPTION,
    lockstep: bool = typer.Option(False, "--lockstep", help="Wait as long as needed for each state (lockstep twin)."),
    campaign_id: str = typer.Option("", "--campaign-id", help="Id in the campaign events (default: random)."),
    campaign_kind: str = typer.Option("control", "--campaign-kind", callback=_check_campaign_kind,
                                      help="Kind in the campaign events: control, identification or jog."),
    idle_timeout: float = typer.Option(10.0, "--idle-timeout", callback=POSITIVE,
                                       help="Give up after this long without any state (s)."),
    instance: str = INSTANCE_OPTION,
    listen: list[str] | None = LISTEN_OPTION,
    connect: list[str] | None = CONNECT_OPTION,
    autoconnect: bool = AUTOCONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """Run the controller on the bus: follows --trajectory, or holds the neck where it is (a
    service: runs the campaigns asked for on xneck/campaign/request and .../request/<instance>)."""
    from bridge.instance_check import NameTaken, check_name_free
    from bridge.runtime import SystemdNotify, raise_priority, setup_logging, stop_on_signals
    from controller.process import ControllerNode, ControllerProcessConfig

    setup_logging(verbose)
    check_endpoints(listen, connect)
    check_credentials()
    params = load_cli_params(params_file, overrides)
    config = law_config(law, no_pulleys)
    traj = load_checked_trajectory(trajectory, params, config) if trajectory else None
    stop = stop_on_signals()
    cfg = ControllerProcessConfig(campaign_id=campaign_id, campaign_kind=campaign_kind, lockstep=lockstep,
                                  idle_timeout_s=idle_timeout, exit_when_done=traj is not None, instance=instance)
    with open_bus(listen, connect, autoconnect) as session:
        try:  # before its tokens (bridge.instance_check); a signal ends its wait
            check_name_free(session, instance, kind="controller", stop=stop)
        except NameTaken as exc:
            raise fail(f"controller not started: {exc}") from None
        if stop.is_set():
            logging.getLogger("xneck.controller").info("controller %s not started: stopped by a signal", instance)
            return
        node = ControllerNode(session, params, config, traj, cfg)
        if not lockstep:
            raise_priority()
        logging.getLogger("xneck.controller").info("controller %s up (%s)", node.instance, config.name)
        systemd = SystemdNotify.from_environ()  # xneck up's watch of its loop (server/cli/up.py), or systemd's
        try:
            outcome = node.run(stop, systemd)
        finally:
            node.close()
            if systemd is not None:
                systemd.close()
        logging.getLogger("xneck.controller").info("controller %s: %s", node.instance, outcome)
    if outcome == "aborted":
        raise typer.Exit(1)
