"""Simulated EPICS IOCs standing in for the real METRIXS beamline (caproto)."""
