"""Training: the algorithms behind ``magail-sumo train``, each a ``train_<name>`` run registered
by name (:mod:`.algorithms`): PPO rewarded by an adversarial imitation discriminator
(GAIL / MAGAIL: :mod:`.gail`, :mod:`.ppo`, :mod:`.reward`, :mod:`.adversarial`), behavioural
cloning (:mod:`.bc`), SAC on a task or GAIL reward (:mod:`.sac`) and the GameFormer predictor
(:mod:`.gameformer`); the run configs (:mod:`.config`), checkpoints and exact resume
(:mod:`.checkpoints`, :mod:`.resume`, :mod:`.rng`, :mod:`.run_dir`) and the entry point
:func:`.trainer.train`.

A checkpoint becomes an evaluation policy one layer up, in :mod:`magail_sumo.policies`.
"""
