"""Training the learned kernel and the learned sign check on the mesh corpus (``nkf train``). Not part
of reconstruction: the core never imports it, and the Blender extension does not bundle it."""
