"""Point-cloud quality metrics and the online quality estimate."""

from edgerecon.quality.metrics import QualityScore, evaluate_clouds, fscore, nearest_distances
from edgerecon.quality.online import (
    CorrelationReport,
    OnlineQuality,
    OnlineQualityConfig,
    online_offline_correlation,
    online_quality,
)

__all__ = [
    "CorrelationReport",
    "OnlineQuality",
    "OnlineQualityConfig",
    "QualityScore",
    "evaluate_clouds",
    "fscore",
    "nearest_distances",
    "online_offline_correlation",
    "online_quality",
]
