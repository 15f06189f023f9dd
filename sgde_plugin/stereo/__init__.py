"""Depth prior construction: virtual pinholes, overlap rectification, matching, back-projection."""
