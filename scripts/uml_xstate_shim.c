/*
 * LD_PRELOAD shim that lets Debian's user-mode Linux run on a host CPU with AMX.
 *
 * UML restores its guest processes' FPU state with ptrace(PTRACE_SETREGSET, NT_X86_XSTATE)
 * using a buffer of its own XSAVE size. The host kernel only accepts a buffer of the full
 * XSAVE size, which AMX's tile data makes larger (~11 KB), and fails with EFAULT: UML then
 * panics with "userspace - ptrace set fp regs failed, errno = 14". This wrapper reads the
 * tracee's whole current state, lays UML's (smaller, standard-format) buffer over its start,
 * and writes the whole buffer back, so every component UML knows is set as UML asked and the
 * rest (the AMX tiles, unused by the guest) stays as it was. Built by scripts/uml_run.py.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <elf.h>
#include <stdarg.h>
#include <string.h>
#include <sys/ptrace.h>
#include <sys/types.h>
#include <sys/uio.h>

static unsigned char full[1 << 16] __attribute__((aligned(64)));

long ptrace(enum __ptrace_request req, ...) {
    static long (*real)(enum __ptrace_request, ...);
    va_list ap;
    va_start(ap, req);
    pid_t pid = va_arg(ap, pid_t);
    void *addr = va_arg(ap, void *);
    void *data = va_arg(ap, void *);
    va_end(ap);
    if (!real)
        real = (long (*)(enum __ptrace_request, ...))dlsym(RTLD_NEXT, "ptrace");
    if (req == PTRACE_SETREGSET && (unsigned long)addr == NT_X86_XSTATE && data) {
        struct iovec *iov = data;
        struct iovec whole = {full, sizeof full};
        if (real(PTRACE_GETREGSET, pid, addr, &whole) == 0 && whole.iov_len > iov->iov_len) {
            memcpy(full, iov->iov_base, iov->iov_len);
            return real(req, pid, addr, &whole);
        }
    }
    return real(req, pid, addr, data);
}
