"""Play an emulated sensor into a pseudo-terminal: a plan from a thread (tests), a recording from a command.

The pty itself (how a reader follows it across drops, how no byte is lost) is :mod:`.pty_port`.
"""
from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from gyronet.recordings.data import load_recording
from gyronet.atomic import write_text
from gyronet.errors import GyronetError
from gyronet.deploy.stream.emulator import FaultPlan, StreamPlan, plan_stream
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream.lpbus_layout import LpBusLayout
from gyronet.deploy.stream.pty_device import Plug, fill_columns, play_device, play_plugs
from gyronet.deploy.stream.pty_port import PtySensor, play

log = logging.getLogger(__name__)


def play_in_thread(plan: StreamPlan | None, link: str | Path, device: EmulatedLpms | None = None,
                   columns: Mapping[str, np.ndarray] | None = None, faults: FaultPlan | None = None,
                   replugs: Sequence[tuple[EmulatedLpms, Mapping[str, np.ndarray]]] = (),
                   preroll_frames: int = 0, **play_options) -> threading.Thread:
    """Play ``plan`` into a new pseudo-terminal at ``link`` from a daemon thread (tests, in-process
    benchmarks); the port is closed and its link removed when the plan ends.

    With ``device``, the pty answers the host's commands first and then plays ``columns`` (with
    ``faults``) framed in the layout the host left (the thread's ``plan`` attribute holds it).
    ``replugs``: then, for each ``(device, columns)``, the sensor is unplugged and comes back as
    that device (its power-on state), answers the host again and plays those columns (``plans``
    holds every plan). ``preroll_frames``: frames each power-up streams before the host talks.
    """
    sensor = PtySensor(link)
    options = {"speed": 0, "reader_timeout_s": 20, "port_down_s": 0.2, **play_options}

    def plug(power_on: EmulatedLpms, values: Mapping[str, np.ndarray]) -> Plug:
        first = {c: float(v[0]) for c, v in fill_columns(values, power_on.layout()).items()}
        return Plug(power_on, lambda layout: plan_stream(fill_columns(values, layout), "lpbus", faults, layout),
                    first if preroll_frames else None)

    def emulate() -> None:
        try:
            if device is None:
                play(plan, sensor, **options)
            else:
                thread.plans = play_plugs([plug(device, columns), *(plug(*again) for again in replugs)], sensor,
                                          preroll_frames=preroll_frames, **options)
                thread.plan = thread.plans[0]
        finally:
            sensor.close()
            sensor.remove_link()

    thread = threading.Thread(target=emulate, daemon=True)
    thread.plan, thread.plans = plan, []
    thread.start()
    return thread


def emulate_file(input_path: str | os.PathLike, protocol: str = "lpbus", speed: float = 1.0,
                 faults: FaultPlan | None = None, layout: LpBusLayout | None = None,
                 csv_columns: Sequence[str] | None = None, link: str | None = None, port_file: str | None = None,
                 log_file: str | os.PathLike | None = None, port_down_s: float = 0.5,
                 reader_timeout_s: float = 30.0, device: EmulatedLpms | None = None,
                 command_wait_s: float = 1.0) -> dict:
    """``emulate_sensor.py``: play a recording into a pty as a sensor would; return the log.

    The log (see :func:`gyronet.deploy.stream.emulator.plan_stream`) is written to ``log_file`` before
    the first sample is sent, since the plan is fixed by the seed. With ``device`` (LP-BUS only),
    the pty first answers the host's commands (``layout`` is then unused: the frames follow the
    layout the host set), and the log also holds the commands received and the final layout.
    """
    sensor = PtySensor(link, port_file)  # a link it must not replace is refused before the recording loads
    recording = load_recording(input_path)
    if device is not None and protocol != "lpbus":
        raise GyronetError("an emulated sensor (sensor.model) speaks LP-BUS: set protocol=lpbus or sensor.model=null")

    def make_plan(frame_layout: LpBusLayout | None) -> StreamPlan:
        columns = recording.columns if device is None else fill_columns(recording.columns, frame_layout)
        try:
            plan = plan_stream(columns, protocol, faults, frame_layout, csv_columns)
        except (ValueError, KeyError) as err:
            raise GyronetError(f"{input_path}: {err}") from None
        plan.log.update(input=str(input_path), speed=speed)
        if device is not None:
            plan.log.update(sensor=device.model, layout=frame_layout.describe(), commands=list(device.commands))
        if log_file is not None:
            write_text(log_file, json.dumps(plan.log) + "\n")
        log.info("%d samples to send as %s, %d intact; faults planned: %s", len(recording), protocol,
                 len(plan.log["good_indices"]), plan.log["expected_faults"] or "none")
        return plan

    plan = None
    try:
        if device is None:
            plan = make_plan(layout)
            play(plan, sensor, speed, reader_timeout_s=reader_timeout_s, port_down_s=port_down_s)
        else:
            plan = play_device(device, make_plan, sensor, speed, command_wait_s=command_wait_s,
                               reader_timeout_s=reader_timeout_s, port_down_s=port_down_s)
        log.info("all sent")
    except KeyboardInterrupt:
        log.info("stopped")
    finally:
        sensor.close()
        sensor.remove_link()
    return plan.log if plan is not None else {}


__all__ = ["PtySensor", "emulate_file", "play", "play_in_thread"]
