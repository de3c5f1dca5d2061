"""EPICS: the beamline's devices and the PV names they use.

The ophyd-async devices (``devices``), their ophyd v1 equivalents (``devices_v1``) and the PV
names both use (``pvs``).
"""
