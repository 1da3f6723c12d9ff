"""Building a phantom (stage after io): from a phantom definition, the frame that holds its wires
(walls, holes, base, landmarks), the printable mesh of it, its drawings, wiring list and build
guide, and the PLUS definition to go with it. Takes a ``Phantom`` (core.geometry), gives files."""
