"""Pure numerical analysis: identification, Kt, efficiency, diagnosis. No I/O."""
