"""The KRC's FRI cycle in this testbench: 1 ms, the rate of the thesis' lab (FRI 1.0 allows
1..100 ms).  The physics steps once per cycle; every layer takes the cycle from here."""

FRI_CYCLE_NS = 1_000_000
FRI_RATE_HZ = 1_000_000_000 // FRI_CYCLE_NS  # FRI cycles per second
