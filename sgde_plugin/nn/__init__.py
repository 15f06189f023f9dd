"""Network parts of SGDE: prior encoding, prior-channel stem, prior losses, reference depth net."""
