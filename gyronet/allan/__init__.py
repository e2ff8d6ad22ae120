"""Allan deviation of gyro rate and the noise terms read from it: arrays in, arrays out.

``deviation`` holds the overlapping Allan deviation (NIST SP 1065 eq. 11); ``noise`` the angle random
walk N, bias instability B and rate random walk K read from its curve (IEEE Std 952-1997 annex C);
``report`` ``allan_report`` and what the commands write from it; ``plot`` the figure. Rate in deg/s,
so ADEV in deg/s; N in deg/sqrt(h), B in deg/h, K in deg/h/sqrt(h).
May import: gyronet.errors, gyronet.atomic, gyronet.recordings.
"""
from gyronet.allan.deviation import log_taus, oadev
from gyronet.allan.noise import BIAS_INSTABILITY_FACTOR, MIN_CLUSTERS, noise_parameters
from gyronet.allan.plot import plot_allan
from gyronet.allan.report import AXES, GAP_FACTOR, allan_report, continuous_segments, format_table, report_to_json

__all__ = ["AXES", "BIAS_INSTABILITY_FACTOR", "GAP_FACTOR", "MIN_CLUSTERS", "allan_report", "continuous_segments",
           "format_table", "log_taus", "noise_parameters", "oadev", "plot_allan", "report_to_json"]
