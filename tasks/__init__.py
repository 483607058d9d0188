"""Prefect tasks (per-frame / per-condition units the flows map over) and the tracking helper."""
