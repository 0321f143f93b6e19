"""Capture: calibrated multi-camera images (and shipped masks, clean plates) from dataset folders."""
