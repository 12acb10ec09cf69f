"""tissue_viz package."""
