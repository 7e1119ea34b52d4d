"""Files in and out: meshes, receiver points and value tables (`meshio`), Mitsuba 3 scenes
(`mitsuba_io`)."""
