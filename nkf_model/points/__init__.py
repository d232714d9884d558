"""Stage 1: the input points: cleaning, the max_points subset, normalising to the unit box, voxel
reduction, noise level, farthest-point sampling and the winding number of an oriented cloud."""
