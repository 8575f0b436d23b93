"""Scoring bundles: on real scenes by the paper's protocol (eval), side by side on held-out
procedural scenes (experiment), with the image and depth metrics both use (metrics)."""
