/*
 * flash.c — erase and program the calibration pages (bank 2). See board.h.
 *
 * RM0444 "Embedded flash memory (FLASH)": "Unlocking the Flash memory" (FLASH_KEYR: KEY1, KEY2),
 * "Flash main memory erase sequences" / "Page erase" (PER, PNB, BKER, STRT; wait BSY1/BSY2),
 * "Flash main memory programming sequences" / "Standard programming" (PG; two 32-bit writes, low word
 * first, at a double-word aligned address of an erased double word; wait BSY; check the error flags),
 * "FLASH status register (FLASH_SR)": error flags are cleared by writing 1; EOP is set only with EOPIE,
 * so success is "not busy and no error flag". A page erase takes 22 ms typical, 40 ms max (the STM32G0
 * datasheets' "Flash memory characteristics", tERASE; the figure was checked against STM32G030's, the
 * same flash, not against DS13560 itself).
 *
 * The code runs from bank 1, so programming bank 2 does not stall instruction fetches (read while
 * write). The flash is locked again after every operation.
 */
#include "board.h"

static void unlock(void)
{
    if ((FLASH_CR & FLASH_CR_LOCK) != 0u) {
        FLASH_KEYR = FLASH_KEY1;
        FLASH_KEYR = FLASH_KEY2;
    }
}

static int32_t wait_idle(void)
{
    uint32_t sr;
    do {
        sr = FLASH_SR;
    } while ((sr & (FLASH_SR_BSY1 | FLASH_SR_BSY2)) != 0u);
    while ((FLASH_SR & FLASH_SR_CFGBSY) != 0u) {
    }
    sr &= FLASH_SR_ERRORS;
    if (sr != 0u) {
        FLASH_SR = sr; /* write 1 to clear */
        return -(int32_t)sr;
    }
    return 0;
}

static int32_t start(void)
{
    int32_t rc = wait_idle(); /* a previous error, if any, is cleared and reported */
    unlock();
    FLASH_SR = FLASH_SR_ERRORS | FLASH_SR_EOP;
    return rc < 0 ? rc : 0;
}

int32_t flash_erase_page(uint32_t pnb)
{
    int32_t rc;
    if (pnb != CAL_PAGE0_PNB && pnb != CAL_PAGE1_PNB) {
        return -1; /* only the calibration pages: never the image */
    }
    (void)start();
    FLASH_CR = FLASH_CR_PER | FLASH_CR_BKER | ((pnb << FLASH_CR_PNB_SHIFT) & FLASH_CR_PNB_MASK);
    FLASH_CR |= FLASH_CR_STRT;
    rc = wait_idle();
    FLASH_CR = FLASH_CR_LOCK;
    return rc;
}

int32_t flash_program_dword(uint32_t addr, uint32_t lo, uint32_t hi)
{
    int32_t rc;
    if ((addr & 7u) != 0u || addr < CAL_PAGE0_ADDR || addr >= FLASH_MEM_BASE + FLASH_MEM_SIZE) {
        return -1;
    }
    (void)start();
    FLASH_CR = FLASH_CR_PG;
    REG32(addr) = lo;
    REG32(addr + 4u) = hi;
    rc = wait_idle();
    FLASH_CR = FLASH_CR_LOCK;
    return rc;
}
