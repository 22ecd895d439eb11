"""Drawing each part: small copies, exposure gains, seams, and the tiled composite."""
