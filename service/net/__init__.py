"""Beyond one machine: the service's frames, health and latest frames on Zenoh (docs/scale.md)."""
