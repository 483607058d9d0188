"""Verification of the simulated weather against real weather (the `verify` stage, being built): `mmd` holds the
two-sample statistics of the fused-feature check."""
