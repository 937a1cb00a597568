"""Deployment security: a site CA and X.509 v3 certificates per role, the router's access-control rules and the
Zenoh configs that use them (``magnet certs``), and Ed25519 signing keys for calibration records (``magnet keys``)."""
