// The loops over vector lanes are built twice, for AVX2 and for the x86-64 baseline, and the CPU
// chooses at load time. Neither build uses FMA, so both give the same bits. QSDEM_BASELINE_ONLY
// (CMake option QSDEM_TARGET_CLONES=OFF, and the tests' second engine) builds the baseline only.
#pragma once

#ifdef QSDEM_BASELINE_ONLY
#define QSDEM_CLONES
#else
#define QSDEM_CLONES [[gnu::target_clones("avx2", "default")]]
#endif
