/* A guest program of known length for checking the instruction counter (insn.c): the loop
 * runs argv[1] iterations of exactly two instructions (subtract and branch). */
#include <stdlib.h>

int main(int argc, char **argv)
{
    long n = argc > 1 ? atol(argv[1]) : 1;
    if (n < 1)
        n = 1;
    __asm__ volatile("1: subs %0, %0, #1\n\tb.ne 1b" : "+r"(n) : : "cc");
    return 0;
}
