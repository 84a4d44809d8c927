"""The step as one generated kernel (see ``step``): row graphs traced from the reference pipeline (``rows``),
lowered to one Program of row ops (``program``, which states the op contract), emitted as C++ (``emit_cpp``) or
CUDA C (``emit_cuda``), kept on disk (``cache``)."""
