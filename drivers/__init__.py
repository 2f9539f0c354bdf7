"""Links to the field (Modbus, CAN, simulated plant servers)."""
