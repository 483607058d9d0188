"""Verification of the simulated weather against real weather (the `verify` stage): `frames` (reference and simulated
frames as fused inputs), `features` and `classifier` (the early-fusion weather classifier and its fused feature),
`mmd` (the two-sample statistics), `table` (Table 1), `figures`."""
