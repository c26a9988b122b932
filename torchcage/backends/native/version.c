/* The digest of the kernel sources this library was built from (set by the build: setup.py or the
 * run-time build in torchcage/backends/native/__init__.py), so that the loader never takes a stale build. */
#ifndef TC_SOURCE_DIGEST
#define TC_SOURCE_DIGEST "unknown"
#endif

const char *tc_source_digest(void) { return TC_SOURCE_DIGEST; }
