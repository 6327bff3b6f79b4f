"""The paper's metrics, one module each: xi, phi, rho_valid, agreement, GT IoU, bootstrap. Where the
authors' code and the project's strict reading differ (absent classes, agreement over images, the
rho_valid frame selection), the convention is a parameter of the metric, set by pairedgta/conf/metric/*.yaml."""
from pairedgta.metrics.agreement import AGREEMENT_MODES, aggregate_agreement, pixel_agreement
from pairedgta.metrics.bootstrap import ratio_ci, spearman_ci
from pairedgta.metrics.prediction_mass import prediction_mass, prediction_mass_from_labels
from pairedgta.metrics.ranking import SELECTIONS, rho_valid, select_frames, spearman
from pairedgta.metrics.reference_consistency import (
    ABSENT_POLICIES,
    ReferenceConsistency,
    class_mean,
    f_from_counts,
    mean_mask,
    precision_from_counts,
    predicted_counts,
    reference_consistency_counts,
    xi_from_counts,
)
from pairedgta.metrics.segmentation import ConfusionMatrix

__all__ = [
    "ReferenceConsistency", "reference_consistency_counts", "xi_from_counts", "class_mean", "mean_mask",
    "precision_from_counts", "f_from_counts", "predicted_counts",
    "ABSENT_POLICIES", "prediction_mass", "prediction_mass_from_labels", "rho_valid", "select_frames", "spearman",
    "SELECTIONS", "pixel_agreement", "aggregate_agreement", "AGREEMENT_MODES", "ratio_ci", "spearman_ci",
    "ConfusionMatrix",
]
