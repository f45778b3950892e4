"""The Mitsuba 3 bridge: a USD stage with fibers, yarns, meshes, lights and cameras to a Mitsuba
scene, the tabulated fiber BCSDF as a Mitsuba plugin, and the integrator it renders with."""
