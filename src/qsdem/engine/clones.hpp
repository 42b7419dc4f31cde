// The loops over vector lanes are built for AVX2 and for the x86-64 baseline (QSDEM_CLONES_WIDE:
// also AVX-512), and the CPU chooses at load time. No build uses FMA and no loop reduces across
// lanes other than by max, so all give the same bits. QSDEM_BASELINE_ONLY
// (CMake option QSDEM_TARGET_CLONES=OFF, and the tests' second engine) builds the baseline only.
#pragma once

#ifdef QSDEM_BASELINE_ONLY
#define QSDEM_CLONES
#define QSDEM_CLONES_WIDE
#else
#define QSDEM_CLONES [[gnu::target_clones("avx2", "default")]]
// Also AVX-512 (8 lanes), for a loop of long independent lane arithmetic (the contacts' narrow
// phase and law, the spheroids' turn); not for a loop bound by memory (the kick, the drift's translation).
#define QSDEM_CLONES_WIDE [[gnu::target_clones("avx512f", "avx2", "default")]]
#endif
