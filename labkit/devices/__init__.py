"""Device interfaces and drivers: cameras (aravis, genicam, sim) and filter sliders."""
