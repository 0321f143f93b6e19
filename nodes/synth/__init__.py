"""Synth: synthetic capture stages with ground truth (procedural scenes, camera rigs, rendering)."""
