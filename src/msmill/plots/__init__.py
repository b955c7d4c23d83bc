"""Matplotlib plots of msmill results (edges layer: no physics)."""
