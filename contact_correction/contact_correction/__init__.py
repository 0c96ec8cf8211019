"""Vision error correction with contact relations between polyhedra (non-linear step, then the linear optimum of Eqs. 2-9)."""
