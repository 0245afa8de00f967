"""Simulation core: vehicle dynamics and (next) the libsumo session."""
