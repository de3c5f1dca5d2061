"""EPICS: the beamline's ophyd-async devices (``devices``), their ophyd v1 equivalents
(``devices_v1``) and the PV names both use (``pvs``)."""
