"""Anchor models: the one base every Scaffold-family decode shares (:mod:`.anchor_model`), the
reference model of Scaffold-GS's structure (:mod:`.reference_model`) and its small trainer
(:mod:`.train_backbone`)."""
