"""The built-in stages of volcap, one subpackage per stage family (capture, key, hull, mesh, eval, export,
synth, ...) and ``common`` (domain code they share). Registered in the ``volcap.nodes`` entry-point group:
the engine imports every module below this package and finds the Node subclasses."""
