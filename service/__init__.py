"""tactile: capacitive tactile sensors → calibrated forces, served live."""
