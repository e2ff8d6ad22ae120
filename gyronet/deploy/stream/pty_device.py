"""An emulated LPMS behind a pseudo-terminal: answer the host's set-up, then stream in the layout it left.

:class:`~gyronet.deploy.stream.lpbus_device.EmulatedLpms` decides the answers; this module moves the
bytes (``select`` on the pty master) and builds the plan once the host is done. A replug
(:class:`Plug`) closes the pty and opens a new one for the sensor as it powers up again (another
``EmulatedLpms``: its power-on settings, its clock from 0), which answers the host's set-up anew.
"""
from __future__ import annotations

import logging
import os
import select
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from gyronet.deploy.stream.emulator import StreamPlan
from gyronet.deploy.stream.lpbus import encode_lpbus
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream.lpbus_layout import LpBusLayout

if TYPE_CHECKING:
    from gyronet.deploy.stream.pty_port import PtySensor

log = logging.getLogger(__name__)


def serve_commands(device: EmulatedLpms, sensor: PtySensor, command_wait_s: float = 1.0, idle_s: float = 2.0,
                   preroll: bytes = b"") -> bool:
    """Answer the host's commands until it puts the sensor back to streaming; False if it sent none.

    ``preroll``: sensor-data frames sent first, as a sensor streams from power-on (the host must
    skip them while it waits for its answers).
    """
    sensor.write(preroll)
    deadline = time.monotonic() + command_wait_s
    while True:
        left_s = deadline - time.monotonic()
        if left_s <= 0:
            return bool(device.commands)
        ready, _, _ = select.select([sensor.master_fd], [], [], left_s)
        if not ready:
            continue
        for reply in device.feed(os.read(sensor.master_fd, 4096)):
            sensor.write(reply)
        if device.commands:
            if device.streaming:
                return True
            deadline = time.monotonic() + idle_s


@dataclass
class Plug:
    """One power-up of an emulated sensor: its state, and the plan it streams once the host is done.

    ``preroll_row``: the values of the frames it streams (in its power-on layout) before the host
    talks to it; ``make_plan``: the plan in the layout the host left.
    """

    device: EmulatedLpms
    make_plan: Callable[[LpBusLayout], StreamPlan]
    preroll_row: Mapping[str, float] | None = None


def play_device(device: EmulatedLpms, make_plan: Callable[[LpBusLayout], StreamPlan], sensor: PtySensor,
                speed: float = 1.0, command_wait_s: float = 1.0, preroll_frames: int = 0,
                preroll_row: Mapping[str, float] | None = None, **play_options) -> StreamPlan:
    """Open the pty, answer the host's set-up, then play ``make_plan(layout the host left)``; return the plan."""
    return play_plugs([Plug(device, make_plan, preroll_row)], sensor, speed, command_wait_s, preroll_frames,
                      **play_options)[0]


def play_plugs(plugs: Sequence[Plug], sensor: PtySensor, speed: float = 1.0, command_wait_s: float = 1.0,
               preroll_frames: int = 0, port_down_s: float = 0.5, **play_options) -> list[StreamPlan]:
    """:func:`play_device` for each power-up in turn, the port unplugged for ``port_down_s`` between them."""
    from gyronet.deploy.stream.pty_port import play

    reader_timeout_s = float(play_options.pop("reader_timeout_s", 30.0))
    drain_timeout_s = float(play_options.get("drain_timeout_s", 10.0))
    plans = []
    for index, plug in enumerate(plugs):
        if index:
            sensor.drain(drain_timeout_s)
            sensor.close()
            log.info("unplugged for %.2f s", port_down_s)
            time.sleep(port_down_s)
        sensor.open()
        sensor.wait_for_reader(reader_timeout_s)
        device = plug.device
        preroll = b"".join(encode_lpbus(plug.preroll_row, device.layout(), device.sensor_id)
                           for _ in range(preroll_frames)) if plug.preroll_row is not None else b""
        talked = serve_commands(device, sensor, command_wait_s, preroll=preroll)
        log.info("emulated %s %s; streaming %s", device.model,
                 "configured by the host" if talked else "not configured", device.layout().describe())
        plans.append(plug.make_plan(device.layout()))
        # a port drop within a plan: the sensor stayed powered (its settings kept), the host may set it up again
        play(plans[-1], sensor, speed, reader_timeout_s=reader_timeout_s, port_down_s=port_down_s, opened=True,
             after_drop=lambda: serve_commands(device, sensor, command_wait_s), **play_options)
    return plans


def fill_columns(columns: Mapping[str, np.ndarray], layout: LpBusLayout) -> dict[str, np.ndarray]:
    """``columns`` with what ``layout`` sends but the recording lacks: 1 g on z, a unit quaternion, else 0."""
    n = len(columns["time_s"])
    out = dict(columns)
    for name in layout.columns:
        if name not in out:
            out[name] = np.full(n, 1.0 if name in ("acc_z_g", "acccal_z_g", "quat_w") else 0.0)
    return out
