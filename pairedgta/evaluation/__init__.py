"""The evaluate stage's jobs, one module each, below the stage (nothing here imports pairedgta.stages):

* `settings`: the metric settings an evaluation is hashed and computed under, checked once;
* `inputs`: which conditions of a group are evaluated, and the decoding of its images in DataLoader workers;
* `metric`, `registry`: what a metric declares, and the one list of the entry's metrics everything else follows;
* `reductions`: the device kernels the metrics' updates call;
* `counting`: one group's forward and every registered metric's reduction and record;
* `tables`: the built-in metrics (xi, agreement, phi/rho_valid, IoU, the label-free estimators' sums);
* `estimator_sums`: the Gram and energy sums of issue 49's estimators (nuclear norm, energy), as metrics;
* `entry`: one model's entry written from its groups: the metrics' tables, group_counts.npz, summary.json;
* `shards`: the partial sums a shard job leaves for the merging run.
"""
