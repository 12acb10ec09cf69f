"""sph_tissue_sim package."""
