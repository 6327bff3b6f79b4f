"""Object detection on the paired scenes (task=detection), the task's work below the stages: ground-truth boxes from
the renderer's instance masks (boxes.py, ground_truth.py, real_boxes.py), its work for each task-neutral stage
(pseudolabel.py, evaluate.py, cityscapes_val.py, model_check.py; pairedgta/tasks.py names them), its metrics
(registry.py) and the detector set-up check (setup_check.py). The detectors themselves are models
(pairedgta/models/detectors.py, detector_contract.py, sources/det_*.py): this package imports them, never the other
way, and imports no stage."""
