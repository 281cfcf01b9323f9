"""Scripts that reproduce the paper's figures (``python -m experiments.u_maze``)."""
