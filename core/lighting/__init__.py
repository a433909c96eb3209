"""Lighting: the lighting prior ``E_g`` of the pbr stage (paper Eq. 6), fitted from posed frames
and the reconstruction's own G-buffers (:mod:`core.lighting.prior`), and the sky-patch transport
its sun search uses (:mod:`core.lighting.sky_transport`)."""
