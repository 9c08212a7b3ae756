"""The paper's shape primitives (§4-§5): polylines and their grouping, discrete curve
evolution, the scan configuration and the map's abstract sensor reading (the map view), the
shape similarity S*, the eq. 5 matching and the two-step matching of §5.3."""
