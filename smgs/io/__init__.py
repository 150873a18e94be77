"""Reading and writing models in interchange formats (the 3DGS PLY)."""
