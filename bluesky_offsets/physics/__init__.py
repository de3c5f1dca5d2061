"""The beamline's physics: the parameter table, geometry, the RML, the METRIXS elements, the effects, the RAYX twin and the torch engine, the noise model."""
