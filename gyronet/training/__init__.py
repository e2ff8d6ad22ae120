"""Training: fit the model (``train``), its starts and capacity, campaigns of runs, GA, the pipeline.

``pipeline`` runs one training end to end (fit, bundle, evaluate, log); ``fleet`` one bundle per
unit. May import: ``gyronet.errors``, ``gyronet.atomic``, ``gyronet.recordings``, ``gyronet.allan``,
``gyronet.figures``, ``gyronet.model``, ``gyronet.bundle``.
"""
