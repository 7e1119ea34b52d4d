"""Files in and out: meshes (`meshio`), receiver points and value tables (`tables`), Mitsuba 3 scenes
(`mitsuba_io`)."""
