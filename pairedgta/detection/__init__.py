"""Object detection on the paired scenes (task=detection): ground-truth boxes from the renderer's instance masks
(boxes.py, ground_truth.py), detectors and their sources (models.py, contract.py, sources/), and the task's work for
each task-neutral stage (pseudolabel.py, evaluate.py, cityscapes_val.py, model_check.py; pairedgta/tasks.py names
them) with its metrics (registry.py). Nothing here imports pairedgta.stages."""
