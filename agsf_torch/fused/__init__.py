"""Fused attitude paths: the same mathematics as the generic filters, on lanes (matrix-major), eager or compiled."""
