"""shapeloc simulator: the office world, laser simulation, trajectories, the Zenoh publisher
(``shapeloc-sim run``), the demo (``python -m sim_publisher.demo``) and the paper's experiment
(``shapeloc-sim experiment``). It sits above :mod:`clients` and uses it like a real robot."""
