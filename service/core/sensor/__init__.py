"""The map and sensor model: one model of the map (segments, normals, the bucket grid and the
distance field), the ray caster, the scoring of poses against the map for a scan, and the
point-to-line solvers (one pose from a prior, many poses in a batch)."""
