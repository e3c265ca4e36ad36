"""Suite-wide test settings.

The tests run many tiny tensor operations, for which intra-op threading costs more than it
gains (measured: several times slower with 2 threads on a busy 2-core machine), so the whole
suite uses one thread. Results are *not* bit-identical across thread counts: reductions are
summed in a different order, so e.g. training the chapter-3 convolutional RKN with 1 vs 2
threads changes its parameters by up to about 1.5e-6. Fixing the thread count here makes the
suite's numbers reproducible; tests that compare with a reference use tolerances well above
that level.
"""

import torch

torch.set_num_threads(1)
