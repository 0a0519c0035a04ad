"""omniformation core: pure, typed math of the paper (no I/O, no threads, no clock, no global RNG)."""
