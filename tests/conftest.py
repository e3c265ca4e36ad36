"""Suite-wide test settings.

The tests run many tiny tensor operations, for which intra-op threading costs more than it
gains (measured: several times slower with 2 threads on a busy 2-core machine), so the whole
suite uses one thread. Results do not depend on the thread count.
"""

import torch

torch.set_num_threads(1)
