"""Deployment: where gyros live. The live serial stream (``stream``: LP-BUS and CSV over pyserial),
flight-stack parameters (``params``, ``as_flown``: PX4, ArduPilot) and C for microcontrollers.

May import: ``gyronet.errors``, ``gyronet.atomic``, ``gyronet.recordings``, ``gyronet.allan``,
``gyronet.figures``, ``gyronet.model``, ``gyronet.bundle``.
"""
