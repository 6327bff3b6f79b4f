"""The evaluate stage's jobs, one module each, below the stage (nothing here imports pairedgta.stages):

* `settings`: the metric settings an evaluation is hashed and computed under, checked once;
* `inputs`: which conditions of a group are evaluated, and the decoding of its images in DataLoader workers;
* `counting`: one group's per-class counts (xi, phi, agreement, IoU) and label-free estimator sums;
* `tables`: those counts summed over groups through the metrics' own update/compute, and the files written;
* `shards`: the partial sums a shard job leaves for the merging run.
"""
