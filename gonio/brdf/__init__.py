"""BRDF models (analytic, by name) and measured BRDF files."""
