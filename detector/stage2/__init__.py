"""Stage 2: object-centred crops -> foreground mask and model coordinates -> pose."""
