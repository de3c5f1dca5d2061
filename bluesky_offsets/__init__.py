"""bluesky-offsets: calibrate the digital twin of a beamline against the real one."""


def __getattr__(name):
    """``bluesky_offsets.load_calibration`` and ``write_calibration``: loaded when first asked for.

    The package itself imports nothing heavy.
    """
    if name in ("load_calibration", "write_calibration"):
        from bluesky_offsets.model import export
        return getattr(export, name)
    raise AttributeError(f"module 'bluesky_offsets' has no attribute {name!r}")
