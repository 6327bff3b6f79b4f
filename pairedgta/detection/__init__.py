"""Object detection on the paired scenes (task=detection): ground-truth boxes from the renderer's instance masks
(boxes.py), detectors (models.py), the task's pseudo-label and evaluate stages and its metrics."""
