"""Geometry shared by every part: rigid transforms (transforms), a georeferenced pair's offset (offset), the
mesh resolution MAC's thresholds scale with (resolution), pose errors and success (metrics) and whether a
pose can be trusted (trust)."""
