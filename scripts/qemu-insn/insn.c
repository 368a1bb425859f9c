/*
 * A QEMU TCG plugin that counts the guest instructions a user-mode program executes, in total
 * over all its threads, and prints the count at exit ("insns N" on stderr). Used by
 * scripts/aarch64-insns to count loglio's instructions per scan on arm64 (the Jetson's
 * instruction set) under qemu-user, where no hardware counter exists.
 *
 * With the argument `profile=FILE` it also writes, at exit, each translated block's guest
 * address and the instructions executed in it ("ADDRESS COUNT" per line, hexadecimal address;
 * a block translated twice has two lines): an exact profile (scripts/aarch64-insns --profile
 * maps the addresses to functions).
 *
 * The plugin API of QEMU 7.2 (plugin API version 1, Debian 12's qemu-user), declared here
 * instead of including QEMU's header (not packaged): only the calls used.
 *   gcc -shared -fPIC -O2 -o insn.so insn.c -lpthread
 *   qemu-aarch64 -plugin ./insn.so[,profile=FILE] PROGRAM ARGS...
 */
#include <inttypes.h>
#include <pthread.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef uint64_t qemu_plugin_id_t;
struct qemu_plugin_tb;
struct qemu_info_t;
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 = 0 };

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id,
                                           void (*cb)(qemu_plugin_id_t, struct qemu_plugin_tb *));
void qemu_plugin_register_vcpu_tb_exec_inline(struct qemu_plugin_tb *tb, enum qemu_plugin_op op,
                                              void *ptr, uint64_t imm);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
uint64_t qemu_plugin_tb_vaddr(const struct qemu_plugin_tb *tb);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, void (*cb)(qemu_plugin_id_t, void *),
                                    void *userdata);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;

/* One counter for every thread: the inline add is not atomic, so two threads adding at once
 * may lose a block's count. Run the program with one compute thread for exact counts. */
static uint64_t insns;

/* The profile: one entry per translated block, in chunks that never move (the inline adds
 * point into them). */
struct block {
    uint64_t vaddr;
    uint64_t count;
};
#define CHUNK 65536
static struct block **chunks;
static size_t n_chunks, n_blocks;
static char *profile_path;
static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;

static struct block *new_block(uint64_t vaddr)
{
    struct block *b = NULL;
    pthread_mutex_lock(&lock);
    if (n_blocks == n_chunks * CHUNK) {
        struct block **c = realloc(chunks, (n_chunks + 1) * sizeof *chunks);
        struct block *fresh = c ? calloc(CHUNK, sizeof **chunks) : NULL;
        if (c)
            chunks = c;
        if (fresh)
            chunks[n_chunks++] = fresh;
    }
    if (n_blocks < n_chunks * CHUNK) {
        b = &chunks[n_blocks / CHUNK][n_blocks % CHUNK];
        b->vaddr = vaddr;
        n_blocks++;
    }
    pthread_mutex_unlock(&lock);
    return b;
}

static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    (void)id;
    uint64_t n = qemu_plugin_tb_n_insns(tb);
    qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &insns, n);
    if (profile_path) {
        struct block *b = new_block(qemu_plugin_tb_vaddr(tb));
        if (b)
            qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &b->count, n);
    }
}

static void on_exit_cb(qemu_plugin_id_t id, void *p)
{
    (void)id;
    (void)p;
    fprintf(stderr, "insns %" PRIu64 "\n", insns);
    if (profile_path) {
        FILE *f = fopen(profile_path, "w");
        if (!f) {
            fprintf(stderr, "insn: cannot write %s\n", profile_path);
            return;
        }
        for (size_t i = 0; i < n_blocks; i++) {
            const struct block *b = &chunks[i / CHUNK][i % CHUNK];
            if (b->count)
                fprintf(f, "%" PRIx64 " %" PRIu64 "\n", b->vaddr, b->count);
        }
        fclose(f);
    }
}

__attribute__((visibility("default"))) int qemu_plugin_install(qemu_plugin_id_t id,
                                                               const struct qemu_info_t *info,
                                                               int argc, char **argv)
{
    (void)info;
    for (int i = 0; i < argc; i++)
        if (strncmp(argv[i], "profile=", 8) == 0)
            profile_path = strdup(argv[i] + 8);
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_atexit_cb(id, on_exit_cb, NULL);
    return 0;
}
