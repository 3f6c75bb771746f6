"""The bus contract both sides import: wire models, key expressions, the sample decoder,
and the Zenoh session configuration."""
