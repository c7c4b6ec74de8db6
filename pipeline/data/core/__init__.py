"""What every source shares: fetching (transport, soda, decoding, fallback), keeping (cache,
vintages), checking (gate, plausibility), and the S/I/R counts of a place (sir_counts)."""
