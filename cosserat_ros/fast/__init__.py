"""The compiled step of the elastic terms: what a measured gain justifies.

Everything here computes what ``core/terms`` computes, faster: the vertex pass four
vertices per SIMD vector (:mod:`.lanes`, :mod:`.simd`), the threads sharing each pass's
work items (:mod:`.workshare`), large meshes stepped tile by tile (:mod:`.plan`), and
the step kernels themselves (:mod:`.step`). ``test/test_fast.py`` compares each against
the scalar terms; ``docs/performance.md`` has what each one bought.
"""
