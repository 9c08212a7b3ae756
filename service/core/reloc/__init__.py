"""Relocalisation: the global search over the map's view index, hypotheses kept over a drive
and judged on its evidence, and the localiser the factory returns for ``shape``, which tracks
with the shape tracker and searches when the pose is unknown or lost."""
