"""Networks of the recovery models: image backbones (``backbone``), heads, discriminator, losses."""
