"""Hull: the volumetric visual hull and the automatic capture box."""
