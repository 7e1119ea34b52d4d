"""The scene model: lights, materials, occluders (`model`) and its JSON format."""
