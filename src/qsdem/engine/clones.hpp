// The loops over vector lanes are built twice, for AVX2 and for the x86-64 baseline, and the CPU
// chooses at load time. Neither build uses FMA, so both give the same bits. QSDEM_BASELINE_ONLY
// (CMake option QSDEM_TARGET_CLONES=OFF, and the tests' second engine) builds the baseline only.
#pragma once

#ifdef QSDEM_BASELINE_ONLY
#define QSDEM_CLONES
#define QSDEM_CLONES_WIDE
#else
#define QSDEM_CLONES [[gnu::target_clones("avx2", "default")]]
// Also AVX-512 (8 lanes), for a loop of long independent lane arithmetic (the spheroids' turn).
#define QSDEM_CLONES_WIDE [[gnu::target_clones("avx512f", "avx2", "default")]]
#endif
