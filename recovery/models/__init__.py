"""Networks of the recovery models: image backbones (:mod:`.backbones`), HMR's regression head
(:mod:`.heads`), HMR-BLSM (:mod:`.hmr`), the pose discriminator (:mod:`.discriminator`), the mesh
autoencoder (:mod:`.mesh_ae`; its convolution and decoder are in :mod:`blsm.spiral`) and image-to-mesh
network (:mod:`.mesh_net`), the PCA baseline (:mod:`.pca`) and the losses (:mod:`.losses`)."""
