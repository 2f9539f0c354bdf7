"""The identification experiment: relay with hysteresis behind an adaptive phase filter, and the Fourier estimates it uses."""
