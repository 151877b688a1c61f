"""Learned graph simulator of morphing grids (SimuLearn's Double GN): features, training, rollout, evaluation.

Modules (each imports torch, numpy, h5py, meshio and data_schema only; never dolfinx, gmsh or fea_factory):
    graph       named feature layout (Field, Term, Block: JOINT, BEAM) and beam/joint incidence
    features    EpisodeFeatures from an episode's key tables; points rebuilt from features
    symmetry    translation to the fixed joint, rotations about z and the mirror (points, vectors, stress tensors)
    pca         per-term PCA and normalisers (torch buffers, saved with the model)
    gn          the GN block: interaction MLPs per directed edge, sum per receiver, update MLPs
    model       Simulator (encoding + SingleGN | DoubleGN core), G(t+1) = G(t) + dG
    packs       feature packs: the EpisodeFeatures of many episodes in one HDF5 file (<data_dir>/features/*.h5),
                read where the episode files are not (a fresh machine: the repository's packs/, scripts/record.py)
    dataset     episode files (or their packs) -> split by episode -> mirror and rotation augmentation -> GraphSet batches
    metrics     multi-step loss, rollout errors relative to the design size
    train       python -m learn.train (conf/train.yaml); checkpoint: load/save (weights_only)
    rollout     rollout(model, episode, steps=10) -> Rollout (answers averaged over rotations / the mirror when the
                model says so: answer_unroll); rollout_many(model, episodes): many designs in one pass;
                compile_rollout for timing/deployment (backend torchscript | aot)
    aot         every step of a rollout an AOTInductor C++ package, cached on disk by model fingerprint and shapes
    shapes      the rebuilt points as a coarse hex mesh (one per joint, two per beam) and hex volumes
    validity    check(model, rollout) -> Verdict (face dislocation, out-of-training-range features)
    evaluate    python -m learn.evaluate (conf/evaluate.yaml): report.json, report.md, plots
    diagnose    python -m learn.diagnose (conf/diagnose.yaml): one-step vs rollout error, train vs held-out
    predict     python -m learn.predict (conf/predict.yaml): one design's morph, ParaView view, verdict
"""
