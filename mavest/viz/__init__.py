"""Visualisation: Rerun recordings and viewers."""
