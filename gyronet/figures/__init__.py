"""Figures and logs people look at: matplotlib plots (``plots``) and TensorBoard writers (``tb``).

May import: ``gyronet.errors``, ``gyronet.atomic``, ``gyronet.recordings``.
"""
