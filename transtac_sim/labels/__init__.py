"""Exact labels: refracted marker projections, bboxes, visibility, intensity centroids."""
