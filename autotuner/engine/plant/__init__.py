"""Process models (transfer function with dead time), their safe expression parser, and the exact ZOH simulator."""
