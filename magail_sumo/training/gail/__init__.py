"""GAIL / MAGAIL with a PPO generator (``algorithm: gail``): the run (:mod:`.run`: env, adversarial
reward, PPO, callbacks, checkpoints and exact resume), masked PPO over agent slots (:mod:`.ppo`)
and its config block (:mod:`.config`). The reward machinery it shares with SAC-GAIL sits one level
up (:mod:`magail_sumo.training.adversarial`, :mod:`magail_sumo.training.reward`).

(No imports here: :mod:`magail_sumo.training.config` imports :mod:`.config`, and the run imports
the training config.)
"""
