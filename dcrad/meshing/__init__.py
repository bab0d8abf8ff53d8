"""The solver's mesh: the patch table, elements, clusters and adaptive refinement."""
