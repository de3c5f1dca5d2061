"""The test suite's pytest plugin (``-p bluesky_offsets.testing`` in pyproject.toml): it pins the BLAS kernels.

Loaded before the installed plugins (zarr's imports numpy), it pins the BLAS kernels in pytest's
own process, which its workers, IOCs and Dask clusters inherit.
"""

from bluesky_offsets.blas import pin_kernels

pin_kernels()
