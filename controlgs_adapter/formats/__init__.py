"""File formats: the library's self-describing safetensors container (:mod:`.safetensors`) and the
files on it: adapters (:mod:`.adapter`) and training checkpoints (:mod:`.checkpoint`); the backbone
codebases' own files, read as data: PLY, ``cfg_args`` and state dicts (:mod:`.backbone`), TorchScript
archives (:mod:`.torchscript`), decoder files (:mod:`.decoders`) and the ``point_cloud/iteration_<N>``
folder layout (:mod:`.layout`)."""
