"""Closed-loop simulation: nonlinear truth, the rendezvous simulator, its guidance link, plots."""
