"""GameFormer level-k trajectory prediction (``algorithm: gameformer``): the supervised run
(:mod:`.run`), its streamed training samples (:mod:`.data`) and its config block (:mod:`.config`).
The model is :mod:`magail_sumo.models.gameformer`; a checkpoint drives scenes as a closed-loop
agent through :mod:`magail_sumo.policies.gameformer`.

(No imports here: :mod:`magail_sumo.training.config` imports :mod:`.config`.)
"""
