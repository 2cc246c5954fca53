"""File formats: the library's self-describing safetensors container (:mod:`.safetensors`) and the
adapter file on it (:mod:`.adapter`); the backbone codebases' own files, read as data: PLY, ``cfg_args``
and state dicts (:mod:`.backbone`), TorchScript archives (:mod:`.torchscript`), decoder files
(:mod:`.decoders`) and the ``point_cloud/iteration_<N>`` folder layout (:mod:`.layout`)."""
