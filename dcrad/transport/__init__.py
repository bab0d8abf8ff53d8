"""Light transport: rays, sampling, shooting, the direct and final gathers, emitters and surfaces."""
