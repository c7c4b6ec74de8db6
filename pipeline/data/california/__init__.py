"""California's 58 counties from CDPH (via the CHHS portal), every vintage kept, and the
reporting-delay model fitted from the vintages' revisions."""
