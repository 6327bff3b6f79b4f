"""The paper's metrics, one module each: xi, phi, rho_valid, agreement, GT IoU, bootstrap."""
from pairedgta.metrics.agreement import pixel_agreement
from pairedgta.metrics.bootstrap import ratio_ci, spearman_ci
from pairedgta.metrics.prediction_mass import prediction_mass, prediction_mass_from_labels
from pairedgta.metrics.ranking import SELECTIONS, rho_valid, select_frames, spearman
from pairedgta.metrics.reference_consistency import ReferenceConsistency, reference_consistency_counts
from pairedgta.metrics.segmentation import ConfusionMatrix

__all__ = [
    "ReferenceConsistency", "reference_consistency_counts", "prediction_mass", "prediction_mass_from_labels",
    "rho_valid", "select_frames", "spearman", "SELECTIONS", "pixel_agreement", "ratio_ci", "spearman_ci",
    "ConfusionMatrix",
]
