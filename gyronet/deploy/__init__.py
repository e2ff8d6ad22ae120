"""Exports that run where gyros live: flight-stack parameters (PX4, ArduPilot) and C for microcontrollers."""
