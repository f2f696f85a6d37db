"""Association layer: putative associations, the consistency graph and the CLIPPER solver."""
