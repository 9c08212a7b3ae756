"""shapeloc simulator: worlds, laser simulation, trajectories and the Zenoh publisher."""
