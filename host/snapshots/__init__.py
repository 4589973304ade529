"""Snapshots: frames grouped by SYNC counter into lattice snapshots (`aggregator`, with its counter
trust and deadline policies), the one feed every consumer reads them from, and chip health."""
