"""The compensator bundle: its format (``schema``), saving and loading (``io``), and running it.

``compensator.Compensator`` applies a bundle causally, offline (``offline``) and live; ``startup``
computes the run's own offset from its first still seconds. May import: ``gyronet.errors``,
``gyronet.atomic``, ``gyronet.recordings``, ``gyronet.allan``, ``gyronet.model``.
"""
