"""The batched front door: `irradiance`, `shade`, `specular` over a scene (`shade`) and their
sharded variant (`sharding`)."""
