"""`relief infer`: a relief from a measured plate, without a height map.

    slopes  the facet-slope density from the plate's transmitted lobe (geometric optics, explicit map)
    synth   a periodic random relief with that slope density (random crossed lenslets)
    lobe    a transmitted lobe's figures (transmittance, centroid, half-maximum edges, plateau)
    job     infer(sample_path, out_dir, seed, progress): inversion, synthesis, forward check, infer.json
"""
