"""The beamline's physics: the parameter table, geometry, the RML, the METRIXS elements, the effects.

Also the twins (RAYX's, and the torch engine) and the noise model.
"""
