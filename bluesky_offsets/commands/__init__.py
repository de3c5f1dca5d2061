"""The ``bluesky-offsets`` command line and its report.

Loading it pins the BLAS kernels (:func:`bluesky_offsets.blas.pin_kernels`) before numpy and torch
load: the commands compute alike on every CPU, and so do the IOCs and workers they start.
"""

from bluesky_offsets.blas import pin_kernels

pin_kernels()
