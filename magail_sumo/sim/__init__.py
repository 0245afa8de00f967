"""Simulation core: the libsumo session (:mod:`.session`, the only code that imports libsumo),
the kinematic bicycle model and its inverse (:mod:`.dynamics`), SUMO's frames (:mod:`.frames`),
its network read as arrays (:mod:`.sumo_map`) and FCD recording and replay files (:mod:`.fcd`)."""
