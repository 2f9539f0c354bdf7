"""Controller parameters and the function blocks: PID unit (PIDU), MCU, SAT, SWU, SELU."""
