"""Point-cloud quality metrics and the online quality estimate."""

from edgerecon.quality.metrics import QualityScore, evaluate_clouds, fscore, nearest_distances

__all__ = ["QualityScore", "evaluate_clouds", "fscore", "nearest_distances"]
